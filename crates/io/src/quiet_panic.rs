//! Code that may panic (third-party parsers on malformed input, libtorch
//! ops on a device's out-of-memory), run so that a
//! panic becomes an error value without "thread 'main' panicked at ..."
//! on stderr: a process-wide panic hook stays silent for panics raised inside
//! [`catch_quiet`] on the current thread and forwards every other panic to
//! the hook that was installed before (Rust's default message, or the
//! application's own).

use std::cell::Cell;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Once;

thread_local! {
    static QUIET: Cell<usize> = const { Cell::new(0) };
}

fn install_hook() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if QUIET.with(Cell::get) == 0 {
                previous(info);
            }
        }));
    });
}

/// Runs `f`; a panic inside it is returned as `Err(message)` without being
/// printed. Panics on other threads, or outside `f`, print as before.
pub fn catch_quiet<R>(f: impl FnOnce() -> R) -> Result<R, String> {
    install_hook();
    QUIET.with(|q| q.set(q.get() + 1));
    let result = catch_unwind(AssertUnwindSafe(f));
    QUIET.with(|q| q.set(q.get() - 1));
    result.map_err(|payload| {
        payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "panicked".to_string())
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_becomes_its_message_and_nesting_is_restored() {
        assert_eq!(catch_quiet(|| 7), Ok(7));
        let e = catch_quiet(|| -> u8 { panic!("bad box {}", 3) }).unwrap_err();
        assert_eq!(e, "bad box 3");
        let e = catch_quiet(|| catch_quiet(|| panic!("inner")).unwrap_err()).unwrap();
        assert_eq!(e, "inner");
        QUIET.with(|q| assert_eq!(q.get(), 0));
    }
}
