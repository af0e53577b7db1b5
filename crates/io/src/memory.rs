//! The machine's memory, and the two checks every size a user or a file
//! gives goes through before it is allocated (`docs/reliability.md`,
//! promise 2):
//!
//! * [`at_most`]: a size against its stated maximum (a named constant where
//!   the size is defined, e.g. `MAX_IMAGE_SIDE`); the error names the flag,
//!   argument or field, the value and the maximum;
//! * [`check_fits`]: a run's estimated peak memory against what this machine
//!   has ([`available_bytes`]), refused up front with the estimate, what is
//!   available and what lowers it.
//!
//! A refused allocation aborts a Rust process (and the Python interpreter
//! that loaded the package): these checks are what stands between an absurd
//! request and an abort. Estimates are floors, documented where they are
//! made: what must be held at once at the least, so a refusal is certain to
//! be right; a run that passes may still run out inside libtorch, which the
//! world model and the trainer report as an error naming the step and the
//! shapes.
//!
//! Sizes are multiplied with [`bytes`], which saturates: an overflowing
//! product is `u64::MAX` bytes, refused like any other estimate beyond the
//! machine.

use std::path::Path;

/// Bytes in a GiB.
pub const GIB: u64 = 1 << 30;

/// A size beyond its maximum, or a run beyond the machine's memory.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MemoryError {
    /// A size beyond its stated maximum.
    #[error("{name} {value}: at most {max} {unit} is supported")]
    TooLarge {
        /// The flag, argument or field (`--samples`, `batch`, `frames`).
        name: String,
        /// The value given.
        value: u64,
        /// Its maximum.
        max: u64,
        /// What it counts (`frames`, `pixels`, `clips`).
        unit: String,
    },
    /// A run whose estimated peak memory exceeds what the machine has.
    #[error(
        "{what} needs at least {} of memory, but {} is available ({origin}); {advice}",
        gib(*estimate_bytes),
        gib(*available_bytes)
    )]
    Exceeds {
        /// What was asked for, with its sizes.
        what: String,
        /// The estimated peak (a floor).
        estimate_bytes: u64,
        /// The memory available to this process.
        available_bytes: u64,
        /// Where the available figure comes from (`MemAvailable`, a cgroup limit).
        origin: String,
        /// What lowers the estimate.
        advice: String,
    },
}

/// `bytes` as GiB with one decimal (`"12.5 GiB"`); beyond a million GiB
/// (an overflowing estimate) as "more than 1000000 GiB".
pub fn gib(bytes: u64) -> String {
    if bytes >= 1_000_000 * GIB {
        "more than 1000000 GiB".to_owned()
    } else {
        format!("{:.1} GiB", bytes as f64 / GIB as f64)
    }
}

/// The product of `sizes` (a count of elements times bytes per element),
/// saturating at `u64::MAX` instead of overflowing.
pub fn bytes(sizes: &[u64]) -> u64 {
    sizes.iter().fold(1u64, |acc, &s| acc.saturating_mul(s))
}

/// `value` of `name` against `max` (`unit`: what it counts, for the
/// message): [`MemoryError::TooLarge`] beyond it.
pub fn at_most(name: &str, value: u64, max: u64, unit: &str) -> Result<(), MemoryError> {
    if value > max {
        return Err(MemoryError::TooLarge {
            name: name.to_owned(),
            value,
            max,
            unit: unit.to_owned(),
        });
    }
    Ok(())
}

/// The memory available to this process and where the figure comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Available {
    /// Bytes.
    pub bytes: u64,
    /// `MemAvailable of /proc/meminfo` or the cgroup limit it came from.
    pub source: String,
}

/// The memory this process can still allocate: the smaller of
/// `MemAvailable` in `/proc/meminfo` and, where this process's cgroup sets
/// a limit (v2 `memory.max`, v1 `memory.limit_in_bytes`), the limit less
/// the cgroup's usage (less its reclaimable inactive file cache). `None`
/// where neither can be read (not Linux).
pub fn available() -> Option<Available> {
    let meminfo = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|t| meminfo_available(&t))
        .map(|bytes| Available {
            bytes,
            source: "MemAvailable of /proc/meminfo".to_owned(),
        });
    let cgroup = cgroup_available(Path::new("/sys/fs/cgroup"));
    match (meminfo, cgroup) {
        (Some(m), Some(c)) => Some(if c.bytes < m.bytes { c } else { m }),
        (m, c) => m.or(c),
    }
}

/// [`available`] in bytes.
pub fn available_bytes() -> Option<u64> {
    available().map(|a| a.bytes)
}

/// Refuses `what` when `estimate_bytes` exceeds [`available_bytes`]
/// ([`MemoryError::Exceeds`], naming the estimate, what is available and
/// `advice`: what lowers it). Where the available memory cannot be read the
/// check passes.
pub fn check_fits(what: &str, estimate_bytes: u64, advice: &str) -> Result<(), MemoryError> {
    check_fits_in(what, estimate_bytes, available().as_ref(), advice)
}

/// [`check_fits`] against `available` (`None`: unknown, passes).
pub fn check_fits_in(
    what: &str,
    estimate_bytes: u64,
    available: Option<&Available>,
    advice: &str,
) -> Result<(), MemoryError> {
    match available {
        Some(a) if estimate_bytes > a.bytes => Err(MemoryError::Exceeds {
            what: what.to_owned(),
            estimate_bytes,
            available_bytes: a.bytes,
            origin: a.source.clone(),
            advice: advice.to_owned(),
        }),
        _ => Ok(()),
    }
}

/// `MemAvailable` of a `/proc/meminfo` text, in bytes.
fn meminfo_available(text: &str) -> Option<u64> {
    let kib: u64 = text
        .lines()
        .find_map(|l| l.strip_prefix("MemAvailable:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kib.saturating_mul(1024))
}

/// A cgroup limit file's value: `None` for `max` (v2) or a value of 2^60
/// and more (v1's "no limit", 2^63 rounded down to a page).
fn limit_value(text: &str) -> Option<u64> {
    let v: u64 = text.trim().parse().ok()?;
    (v < 1 << 60).then_some(v)
}

/// A `memory.stat` field's value.
fn stat_value(text: &str, key: &str) -> Option<u64> {
    text.lines().find_map(|l| {
        let (k, v) = l.split_once(' ')?;
        (k == key).then(|| v.trim().parse().ok())?
    })
}

/// What this process's cgroup still allows under `root` (normally
/// `/sys/fs/cgroup`): v2 (`memory.max`, `memory.current`, `inactive_file`
/// of `memory.stat`) at the root of a namespaced mount, else v1 (its
/// `memory/` controller). `None` without a limit.
fn cgroup_available(root: &Path) -> Option<Available> {
    let read = |p: &Path| std::fs::read_to_string(p).ok();
    let v2 = (
        root.join("memory.max"),
        root.join("memory.current"),
        root.join("memory.stat"),
        "inactive_file",
    );
    let v1_dir = root.join("memory");
    let v1 = (
        v1_dir.join("memory.limit_in_bytes"),
        v1_dir.join("memory.usage_in_bytes"),
        v1_dir.join("memory.stat"),
        "total_inactive_file",
    );
    [v2, v1].into_iter().find_map(|(limit, usage, stat, key)| {
        let max = limit_value(&read(&limit)?)?;
        let used = read(&usage)
            .and_then(|t| t.trim().parse::<u64>().ok())
            .unwrap_or(0);
        let cache = read(&stat).and_then(|t| stat_value(&t, key)).unwrap_or(0);
        Some(Available {
            bytes: max.saturating_sub(used.saturating_sub(cache)),
            source: format!("the cgroup limit {}", limit.display()),
        })
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn sizes_multiply_without_overflow_and_print_in_gib() {
        assert_eq!(bytes(&[10_000, 16_384, 16_384, 2]), 5_368_709_120_000);
        assert_eq!(bytes(&[u64::MAX, 2]), u64::MAX);
        assert_eq!(bytes(&[]), 1);
        assert_eq!(gib(3 * GIB / 2), "1.5 GiB");
        assert_eq!(gib(u64::MAX), "more than 1000000 GiB");
    }

    #[test]
    fn a_size_beyond_its_maximum_names_it_and_the_maximum() {
        assert!(at_most("--samples", 64, 65_536, "samples").is_ok());
        let e = at_most("--samples", 65_537, 65_536, "samples").unwrap_err();
        assert_eq!(
            e.to_string(),
            "--samples 65537: at most 65536 samples is supported"
        );
    }

    #[test]
    fn an_estimate_beyond_what_is_available_is_refused_with_both_figures() {
        let a = Available {
            bytes: 8 * GIB,
            source: "MemAvailable of /proc/meminfo".into(),
        };
        assert!(check_fits_in("x", 8 * GIB, Some(&a), "lower it").is_ok());
        assert!(check_fits_in("x", u64::MAX, None, "lower it").is_ok());
        let e = check_fits_in(
            "rendering 10000 frames of 16384x16384",
            bytes(&[10_000, 16_384, 16_384, 2]),
            Some(&a),
            "render fewer frames",
        )
        .unwrap_err();
        let text = e.to_string();
        assert!(
            text.starts_with("rendering 10000 frames of 16384x16384 needs at least 5000.0 GiB"),
            "{text}"
        );
        assert!(
            text.contains("but 8.0 GiB is available (MemAvailable of /proc/meminfo)"),
            "{text}"
        );
        assert!(text.ends_with("; render fewer frames"), "{text}");
        // The machine this runs on has less than an exabyte.
        let e = check_fits("an exabyte", 1 << 60, "less").unwrap_err();
        assert!(matches!(e, MemoryError::Exceeds { .. }) || available().is_none());
    }

    #[test]
    fn meminfo_and_cgroup_files_are_read() {
        let meminfo = "MemTotal:       24000000 kB\nMemFree:  100 kB\nMemAvailable:   2000000 kB\n";
        assert_eq!(meminfo_available(meminfo), Some(2_048_000_000));
        assert_eq!(meminfo_available("MemTotal: 5 kB\n"), None);
        assert_eq!(limit_value("max\n"), None);
        assert_eq!(limit_value("9223372036854771712\n"), None);
        assert_eq!(limit_value("4294967296\n"), Some(4 * GIB));

        let dir = tempfile::tempdir().unwrap();
        assert_eq!(cgroup_available(dir.path()), None);
        // v2: 4 GiB limit, 3 GiB used of which 1 GiB is inactive file cache.
        std::fs::write(dir.path().join("memory.max"), "4294967296\n").unwrap();
        std::fs::write(dir.path().join("memory.current"), "3221225472\n").unwrap();
        std::fs::write(
            dir.path().join("memory.stat"),
            "anon 1\nactive_file 2\ninactive_file 1073741824\n",
        )
        .unwrap();
        let a = cgroup_available(dir.path()).unwrap();
        assert_eq!(a.bytes, 2 * GIB);
        assert!(a.source.contains("memory.max"), "{}", a.source);
        // No v2 limit: v1's controller.
        std::fs::write(dir.path().join("memory.max"), "max\n").unwrap();
        assert_eq!(cgroup_available(dir.path()), None);
        let v1 = dir.path().join("memory");
        std::fs::create_dir(&v1).unwrap();
        std::fs::write(v1.join("memory.limit_in_bytes"), "2147483648\n").unwrap();
        std::fs::write(v1.join("memory.usage_in_bytes"), "1073741824\n").unwrap();
        let a = cgroup_available(dir.path()).unwrap();
        assert_eq!(a.bytes, GIB);
        if cfg!(target_os = "linux") {
            assert!(available_bytes().is_some_and(|b| b > 0));
        }
    }
}
