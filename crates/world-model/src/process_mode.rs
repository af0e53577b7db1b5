//! Process-wide modes an environment variable chooses (`BRIDGEV2W_CPU_BF16`,
//! `BRIDGEV2W_CPU_LINEAR`, `BRIDGEV2W_CPU_ATTENTION`): one cell type keeps
//! each resolved mode in a static, set at start-up (`init_from_env`, which
//! the binary and the Python module call) or by `set`, and read on every
//! call without a lock.

use crate::error::WorldModelError;
use std::str::FromStr;
use std::sync::atomic::{AtomicU8, Ordering};

/// A mode chosen for the whole process by the environment variable [`ENV`].
///
/// [`ENV`]: ProcessMode::ENV
pub trait ProcessMode:
    Copy + Default + PartialEq + FromStr<Err = WorldModelError> + 'static
{
    /// The environment variable naming the mode.
    const ENV: &'static str;
    /// Every variant (`named_enum!`'s `ALL`).
    const VARIANTS: &'static [Self];
    /// The mode decided for this machine (what `Auto` means here, or a
    /// fallback where the chosen one cannot run).
    fn resolve(self) -> Self;
}

/// Where one [`ProcessMode`] lives: a `static` holding the resolved mode.
#[derive(Debug)]
pub struct ModeCell(AtomicU8);

impl ModeCell {
    /// Not set yet: the first read resolves the default.
    pub const fn new() -> Self {
        Self(AtomicU8::new(0))
    }

    /// Sets the mode (resolved).
    pub fn set<M: ProcessMode>(&self, mode: M) {
        let resolved = mode.resolve();
        let index = M::VARIANTS.iter().position(|v| *v == resolved).unwrap_or(0);
        self.0.store(index as u8 + 1, Ordering::Relaxed);
    }

    /// The mode in effect (resolved); the default resolved until set.
    pub fn get<M: ProcessMode>(&self) -> M {
        match self.0.load(Ordering::Relaxed) {
            0 => {
                self.set(M::default());
                self.get()
            }
            code => M::VARIANTS[usize::from(code - 1)],
        }
    }

    /// Sets the mode from [`ProcessMode::ENV`] (unset: the default) and
    /// returns it resolved; an unknown value is an error naming the
    /// variable, the value and the choices.
    pub fn init_from_env<M: ProcessMode>(&self) -> Result<M, WorldModelError> {
        let mode = match std::env::var(M::ENV) {
            Ok(v) => v.trim().parse()?,
            Err(_) => M::default(),
        };
        self.set(mode);
        Ok(self.get())
    }
}

impl Default for ModeCell {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
    enum Speed {
        #[default]
        Auto,
        Slow,
        Fast,
    }
    crate::named_enum!(Speed, WorldModelError, WorldModelError::input, "BV2W_TEST_SPEED", {
        Auto => "auto",
        Slow => "slow",
        Fast => "fast",
    });
    impl ProcessMode for Speed {
        const ENV: &'static str = "BV2W_TEST_SPEED";
        const VARIANTS: &'static [Self] = Self::ALL;
        fn resolve(self) -> Self {
            match self {
                Self::Auto => Self::Fast,
                other => other,
            }
        }
    }

    #[test]
    fn unset_reads_the_resolved_default_and_set_stores_resolved_modes() {
        let cell = ModeCell::new();
        assert_eq!(cell.get::<Speed>(), Speed::Fast);
        cell.set(Speed::Slow);
        assert_eq!(cell.get::<Speed>(), Speed::Slow);
        cell.set(Speed::Auto);
        assert_eq!(cell.get::<Speed>(), Speed::Fast);
    }

    #[test]
    fn the_environment_chooses_and_a_bad_value_names_the_variable() {
        let cell = ModeCell::new();
        std::env::set_var("BV2W_TEST_SPEED", " slow ");
        assert_eq!(cell.init_from_env::<Speed>().unwrap(), Speed::Slow);
        std::env::set_var("BV2W_TEST_SPEED", "warp");
        let err = cell.init_from_env::<Speed>().unwrap_err().to_string();
        assert!(
            err.contains("BV2W_TEST_SPEED") && err.contains("warp"),
            "{err}"
        );
        std::env::remove_var("BV2W_TEST_SPEED");
        assert_eq!(cell.init_from_env::<Speed>().unwrap(), Speed::Fast);
    }
}
