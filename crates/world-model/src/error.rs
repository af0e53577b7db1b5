//! Errors of the world-model crate: every variant names the file, key or value at fault.

use std::path::PathBuf;

/// Errors from loading configs and weights, running models and parity fixtures.
#[derive(Debug, thiserror::Error)]
pub enum WorldModelError {
    /// A file could not be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// A JSON file is malformed or does not match the expected schema.
    #[error("{path}: invalid JSON: {error}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: serde_json::Error,
    },
    /// A config value is out of range or inconsistent with another.
    #[error("{path}: config field `{field}`: {message}")]
    Config {
        /// The config file (or a preset's name).
        path: PathBuf,
        /// The field at fault.
        field: String,
        /// What was expected.
        message: String,
    },
    /// A parameter of the model has no tensor in the weight files.
    #[error("missing weight `{key}` (expected shape {expected:?}) in {files}")]
    MissingWeight {
        /// The parameter's key (diffusers naming).
        key: String,
        /// The model's shape for it.
        expected: Vec<i64>,
        /// The weight files searched.
        files: String,
    },
    /// A tensor in the weight files matches no parameter of the model.
    #[error(
        "{path}: unexpected weight `{key}` (the model has no such parameter; is the config right?)"
    )]
    UnexpectedWeight {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
    },
    /// A tensor in the weight files has another shape than the model's parameter.
    #[error("{path}: weight `{key}` has shape {found:?}, the model expects {expected:?} (is the config right?)")]
    ShapeMismatch {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
        /// The model's shape.
        expected: Vec<i64>,
        /// The file's shape.
        found: Vec<i64>,
    },
    /// A tensor in the weight files holds NaN or infinite values.
    #[error("{path}: weight `{key}` holds {count} NaN or infinite value(s) (a diverged run or a corrupt file)")]
    NonFiniteWeight {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
        /// How many values are not finite.
        count: i64,
    },
    /// Values became NaN or infinite while a model ran (a diverged chain):
    /// where, and which settings or files to check.
    #[error("NaN or infinite values {during}: {check}")]
    NonFinite {
        /// Where they appeared (the step and the tensor).
        during: String,
        /// What can cause it, with the values in use.
        check: String,
    },
    /// An input has the wrong shape, range or type.
    #[error("invalid input `{name}`: {message}")]
    Input {
        /// The input's name.
        name: String,
        /// What was expected.
        message: String,
    },
    /// An error from libtorch.
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),
    /// The device ran out of memory during an operation.
    #[error("out of device memory while {during}: {figures}\n{advice}")]
    OutOfMemory {
        /// What was running, with its shapes.
        during: String,
        /// libtorch's account: the allocation that failed and the memory in use.
        figures: String,
        /// What lowers the memory of what was running.
        advice: &'static str,
    },
    /// A size beyond its stated maximum, or a prediction whose estimated
    /// memory exceeds what the machine has (refused before it runs).
    #[error(transparent)]
    Memory(#[from] bridgev2w_io::memory::MemoryError),
    /// A model name is neither a local folder nor in the Hugging Face cache.
    #[error("model {name}: not found (offline); looked at:\n  - {}\nGive a diffusers folder, or download it first (e.g. `huggingface-cli download {name}`; HF_HUB_CACHE or HF_HOME name the cache)", looked.join("\n  - "))]
    ModelNotFound {
        /// The name given.
        name: String,
        /// Each place looked at, and why it did not hold the model.
        looked: Vec<String>,
    },
    /// A Hub model name (`OWNER/NAME@REVISION`) refused: a revision that is
    /// not a plain name, or a cache entry that leads outside its folder.
    #[error("model name {name:?}: {message}")]
    ModelName {
        /// The name given.
        name: String,
        /// What is wrong, and what was expected (never a file's content).
        message: String,
    },
    /// Loading a model folder failed.
    #[error("loading the model from {}", path.display())]
    Load {
        /// The folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: Box<WorldModelError>,
    },
    /// Running a parity fixture failed.
    #[error("parity fixture {}", path.display())]
    Fixture {
        /// The fixture folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: Box<WorldModelError>,
    },
}

/// Result alias of this crate.
pub type Result<T, E = WorldModelError> = std::result::Result<T, E>;

impl WorldModelError {
    /// This error, as one of loading the model folder `dir`.
    pub fn in_folder(self, dir: &std::path::Path) -> Self {
        Self::Load {
            path: dir.to_path_buf(),
            source: Box::new(self),
        }
    }

    /// An out-of-memory error from libtorch as [`Self::OutOfMemory`] while
    /// `during()` (what ran, with its shapes), with `advice` (e.g.
    /// [`PREDICT_MEMORY_ADVICE`]); other errors unchanged.
    pub fn on_out_of_memory(self, during: impl FnOnce() -> String, advice: &'static str) -> Self {
        match self {
            Self::Torch(e) => match out_of_memory_figures(&e.to_string()) {
                Some(figures) => Self::OutOfMemory {
                    during: during(),
                    figures,
                    advice,
                },
                None => Self::Torch(e),
            },
            other => other,
        }
    }

    /// A caught panic's message as an error ([`Self::Torch`]: libtorch's ops
    /// panic with its message, e.g. on a failed allocation, which
    /// [`Self::on_out_of_memory`] then recognises).
    pub fn from_panic(message: String) -> Self {
        Self::Torch(tch::TchError::Torch(message))
    }

    pub(crate) fn io(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            error,
        }
    }

    pub(crate) fn config(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Self::Config {
            path: path.into(),
            field: field.into(),
            message: message.into(),
        }
    }

    pub(crate) fn input(name: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Input {
            name: name.into(),
            message: message.into(),
        }
    }
}

impl From<bridgev2w_io::FileError> for WorldModelError {
    fn from(e: bridgev2w_io::FileError) -> Self {
        use bridgev2w_io::FileError;
        match e {
            FileError::Io { path, source } => Self::Io {
                path,
                error: source,
            },
            FileError::Json { path, source } => Self::Json {
                path,
                error: source,
            },
            FileError::Format { path, message } => Self::Input {
                name: path.display().to_string(),
                message,
            },
        }
    }
}

/// Runs `f`; a panic inside it (libtorch's ops panic on their errors, a
/// device's out-of-memory among them) becomes [`WorldModelError::Torch`]
/// with its message, without "panicked at" on stderr.
pub fn guarded<T>(f: impl FnOnce() -> Result<T>) -> Result<T> {
    bridgev2w_io::quiet_panic::catch_quiet(f)
        .unwrap_or_else(|panic| Err(WorldModelError::from_panic(panic)))
}

/// What lowers a prediction's memory, for [`WorldModelError::OutOfMemory`].
pub const PREDICT_MEMORY_ADVICE: &str =
    "Lower the batch (predict --batch-size, plan --max-batch), use --precision bf16, or keep the VAE tiled";

/// What lowers `bench model`'s memory, for [`WorldModelError::OutOfMemory`].
pub const BENCH_MEMORY_ADVICE: &str =
    "Lower --batch, --frames or the size, use --precision bf16, or --vae-tiling";

/// The line of a libtorch error that says the memory ran out, with its
/// figures (CUDA's caching allocator: "CUDA out of memory. Tried to allocate
/// ..."; this project's CPU allocator: "... out of memory allocating N
/// bytes"; libtorch's own CPU allocator: "... can't allocate memory: you
/// tried to allocate N bytes ..." or "... not enough memory: ..."), without
/// libtorch's backtrace; `None` for any other error.
pub fn out_of_memory_figures(text: &str) -> Option<String> {
    const SIGNS: [&str; 3] = [
        "out of memory",
        "can't allocate memory",
        "not enough memory",
    ];
    // An op's panic carries tch's error in its Debug form (`called
    // `Result::unwrap()` on an `Err` value: Torch("...")`), newlines escaped.
    let text = text.replace("\\n", "\n");
    let line = text.lines().find(|l| SIGNS.iter().any(|s| l.contains(s)))?;
    let line = line.split_once("Torch(\"").map_or(line, |(_, rest)| rest);
    Some(
        line.trim()
            .trim_start_matches("Internal torch error: ")
            .to_owned(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_memory_lines_of_each_allocator_are_recognised() {
        let cpu = "Internal torch error: DefaultCPUAllocator: not enough memory: you tried to allocate 1099511627776 bytes.\nException raised from ...";
        assert_eq!(
            out_of_memory_figures(cpu).as_deref(),
            Some("DefaultCPUAllocator: not enough memory: you tried to allocate 1099511627776 bytes.")
        );
        let default = "Internal torch error: [enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to allocate 695784701952 bytes. Error code 12 (Cannot allocate memory)\nframe #0: ...";
        assert_eq!(
            out_of_memory_figures(default).as_deref(),
            Some("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to allocate 695784701952 bytes. Error code 12 (Cannot allocate memory)")
        );
        // As an op's panic (tch's unwrap of its error, Debug-formatted).
        let panic = r#"called `Result::unwrap()` on an `Err` value: Torch("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79.19 GiB of which 1.10 GiB is free.\nException raised from malloc at CUDACachingAllocator.cpp:1574 (most recent call first):\nframe #0: c10::Error::Error")"#;
        assert_eq!(
            out_of_memory_figures(panic).as_deref(),
            Some("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79.19 GiB of which 1.10 GiB is free.")
        );
        let ours = "bridgev2w CPU allocator: out of memory allocating 4096 bytes";
        assert_eq!(out_of_memory_figures(ours).as_deref(), Some(ours));
        assert_eq!(out_of_memory_figures("shape '[2, 3]' is invalid"), None);
    }

    #[test]
    fn an_out_of_memory_names_what_ran_and_keeps_libtorchs_figures() {
        // libtorch's message as a caught panic of an op carries it.
        let torch = "Internal torch error: CUDA out of memory. Tried to allocate 10.55 GiB. GPU 0 has a total capacity of 139.80 GiB of which 10.40 GiB is free.\nException raised from malloc at CUDACachingAllocator.cpp:1574 (most recent call first):\nframe #0: ...";
        let e = WorldModelError::from_panic(torch.to_owned()).on_out_of_memory(
            || "predicting 4 clip(s) of 25 frames at 480x720".to_owned(),
            PREDICT_MEMORY_ADVICE,
        );
        let text = e.to_string();
        assert!(matches!(e, WorldModelError::OutOfMemory { .. }), "{text}");
        assert!(
            text.contains("predicting 4 clip(s) of 25 frames at 480x720"),
            "{text}"
        );
        assert!(
            text.contains("Tried to allocate 10.55 GiB") && text.contains("139.80 GiB"),
            "{text}"
        );
        assert!(
            !text.contains("frame #0") && !text.contains("Internal torch error"),
            "{text}"
        );
        assert!(
            text.contains("--max-batch") && text.contains("bf16"),
            "{text}"
        );
        // Other errors pass unchanged, and `during` is not evaluated for them.
        let other = WorldModelError::from_panic("shape mismatch".to_owned()).on_out_of_memory(
            || unreachable!("only for out-of-memory"),
            PREDICT_MEMORY_ADVICE,
        );
        assert!(matches!(other, WorldModelError::Torch(_)), "{other}");
        let input = WorldModelError::input("x", "bad")
            .on_out_of_memory(|| unreachable!(), PREDICT_MEMORY_ADVICE);
        assert!(matches!(input, WorldModelError::Input { .. }));
    }
}
