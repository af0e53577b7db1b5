//! Modes named by strings in configs and on the command line: one macro
//! writes their `NAMES`, `FromStr` (an unknown name is an error listing the
//! names), `Display` and the list of variants, so every typed mode parses
//! and prints alike.

/// For an enum of unit variants:
/// `named_enum!(Mode, ErrorType, ErrorType::input, "field", { A => "a", B => "b" });`
/// adds `Mode::NAMES`, `FromStr` (errors through `ErrorType::input(field,
/// message)`) and `Display`.
#[macro_export]
macro_rules! named_enum {
    ($ty:ident, $err:ty, $ctor:path, $field:expr, { $($variant:ident => $name:literal),+ $(,)? }) => {
        impl $ty {
            /// The names [`std::str::FromStr`] accepts.
            pub const NAMES: &'static [&'static str] = &[$($name),+];
            /// Every variant, in the order of [`Self::NAMES`].
            #[allow(dead_code)]
            pub const ALL: &'static [Self] = &[$(Self::$variant),+];
        }

        impl ::std::str::FromStr for $ty {
            type Err = $err;
            fn from_str(s: &str) -> ::std::result::Result<Self, $err> {
                match s {
                    $($name => Ok(Self::$variant),)+
                    other => Err($ctor(
                        $field,
                        format!("{other:?}: expected one of {}", Self::NAMES.join(", ")),
                    )),
                }
            }
        }

        impl ::std::fmt::Display for $ty {
            fn fmt(&self, f: &mut ::std::fmt::Formatter<'_>) -> ::std::fmt::Result {
                f.write_str(match self {
                    $(Self::$variant => $name,)+
                })
            }
        }
    };
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use crate::error::WorldModelError;

    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Colour {
        Red,
        DarkBlue,
    }
    named_enum!(Colour, WorldModelError, WorldModelError::input, "colour", {
        Red => "red",
        DarkBlue => "dark_blue",
    });

    #[test]
    fn names_parse_print_and_an_unknown_one_lists_them() {
        assert_eq!("dark_blue".parse::<Colour>().unwrap(), Colour::DarkBlue);
        assert_eq!(Colour::Red.to_string(), "red");
        assert_eq!(Colour::NAMES, ["red", "dark_blue"]);
        let e = "green".parse::<Colour>().unwrap_err().to_string();
        assert!(
            e.contains("colour") && e.contains("\"green\"") && e.contains("red, dark_blue"),
            "{e}"
        );
    }
}
