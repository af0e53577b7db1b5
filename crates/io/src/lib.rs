//! The utilities every bridgev2w crate shares, each with one home (files
//! mostly, hence the name; also the seeds and the peer processes that the
//! benchmarks and tests compare against):
//!
//! * [`atomic`]: files written through a synced temporary file and a rename,
//!   so a reader (or a killed run) sees the old file or the new one, never a
//!   part;
//! * [`json`]: JSON files read and written with errors that name the file;
//! * [`npy`] and [`png`]: NumPy arrays and PNG images, the formats masks,
//!   frames and videos are exchanged in;
//! * [`frame`]: [`frame::RgbFrame`], the float RGB frame that the world
//!   model, the planners and the metrics all use, and its 8-bit conversions;
//! * [`output`]: output folders as transactions (built in a temporary folder the run owns, renamed
//!   to `OUT` when complete);
//! * [`sections`]: a markdown results file that several commands share, each
//!   owning one marked section;
//! * [`seed`]: seeded, reproducible randomness (seed mixing, SplitMix64,
//!   normal draws);
//! * [`peer`]: the Python peers of the benches (repository root, venvs,
//!   scripts that print a JSON result);
//! * [`progress`]: [`progress::Progress`], how a library reports stages,
//!   steps and notes while it runs (the command-line tool draws the bars);
//! * [`realdata`]: where the real robot episodes of the tests are
//!   (`../shared/realdata/`), and the skip message where they are absent;
//! * [`confine`]: names read from files kept inside their folder;
//! * [`memory`]: the machine's available memory, sizes checked against
//!   their stated maximum and a run's estimated peak against the machine
//!   before anything is allocated;
//! * [`quiet_panic`]: code that may panic (third-party parsers, libtorch
//!   ops, which panic on a device's out-of-memory) run so that the panic
//!   becomes an error value;
//! * `plot` (feature `plot`): the PNG figures of the results files (line
//!   panels, grouped bars, scatter plots with a fitted line).

pub mod atomic;
pub mod confine;
pub mod frame;
pub mod json;
pub mod memory;
pub mod npy;
pub mod output;
pub mod peer;
#[cfg(feature = "plot")]
pub mod plot;
pub mod png;
pub mod progress;
pub mod quiet_panic;
pub mod realdata;
pub mod sections;
pub mod seed;

use std::path::{Path, PathBuf};

/// A file that could not be read, written or parsed: always names the file.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The operating system refused.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not valid JSON, or not the JSON expected.
    #[error("{}: {source}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// Where and why.
        source: serde_json::Error,
    },
    /// The content is not what was expected.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What was found and what was expected.
        message: String,
    },
}

impl FileError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// `path`'s content is not what was expected.
    pub fn format(path: &Path, message: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, FileError>;
