//! The font of the figures' text: a TrueType file found at run time (none
//! is compiled in), registered with plotters' `ab_glyph` text renderer once
//! per process.
//!
//! The search list: the file named by [`FONT_ENV`] (an error if it is set
//! and unusable), then DejaVu Sans where Linux distributions install it,
//! then the copy `scripts/setup-venv.sh` unpacks into the project venv
//! (`.venv/fonts/DejaVuSans.ttf`, from Debian's `fonts-dejavu-core`,
//! without root). When none is found the figures are still written, without
//! text (axes, grid, lines, bars and points only), and
//! [`missing_font_warning`] says how to get the text.

use super::PlotError;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The environment variable naming the TrueType (`.ttf`) file of the text.
pub const FONT_ENV: &str = "BRIDGEV2W_FONT";

/// The family name the font is registered under. Every text style of the
/// figures names it, so that no text is ever drawn in a family that was not
/// registered.
pub(crate) const FAMILY: &str = "bridgev2w-sans";

/// DejaVu Sans where distributions install it (Debian/Ubuntu, Arch, Fedora).
const SYSTEM_FONTS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
];

/// Where `scripts/setup-venv.sh` unpacks the font, relative to the
/// repository root.
pub const VENV_FONT: &str = ".venv/fonts/DejaVuSans.ttf";

/// The files tried, in order, after [`FONT_ENV`]: the system's DejaVu Sans,
/// then the project venv's copy (relative to the working folder, then to the
/// repository this program was built from).
pub fn font_search_list() -> Vec<PathBuf> {
    let mut list: Vec<PathBuf> = SYSTEM_FONTS.iter().map(PathBuf::from).collect();
    list.push(PathBuf::from(VENV_FONT));
    list.push(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../..")
            .join(VENV_FONT),
    );
    list
}

/// The outcome of the one search per process: the registered file, none
/// found, or an unusable [`FONT_ENV`] file (the message).
static FONT: OnceLock<Result<Option<PathBuf>, String>> = OnceLock::new();

/// Reads and registers `path` (kept for the process's lifetime, as plotters
/// needs).
fn register(path: &Path) -> Result<(), String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font(FAMILY, plotters::style::FontStyle::Normal, bytes)
        .map_err(|_| "not a TrueType/OpenType font".to_string())
}

fn search() -> Result<Option<PathBuf>, String> {
    if let Some(named) = std::env::var_os(FONT_ENV).filter(|v| !v.is_empty()) {
        let path = PathBuf::from(named);
        return register(&path)
            .map(|()| Some(path.clone()))
            .map_err(|e| format!("{FONT_ENV}={}: {e}", path.display()));
    }
    Ok(font_search_list()
        .into_iter()
        .find(|p| p.is_file() && register(p).is_ok()))
}

/// The font file of the figures' text, registered on first use; `None` when
/// none was found (the figures are drawn without text). An error when
/// [`FONT_ENV`] names a file that cannot be read or is not a font.
pub fn text_font() -> Result<Option<&'static Path>, PlotError> {
    match FONT.get_or_init(search) {
        Ok(found) => Ok(found.as_deref()),
        Err(message) => Err(PlotError::Font(message.clone())),
    }
}

/// A warning for the person running the command when the figures have no
/// text for want of a font (`None` when they have text).
pub fn missing_font_warning() -> Option<String> {
    match text_font() {
        Ok(None) => Some(format!(
            "warning: no font found for the figures' text (tried {} and {}); the figures were drawn without text. Set {FONT_ENV} to a .ttf file (or run scripts/setup-venv.sh, which unpacks DejaVu Sans into .venv/fonts/).",
            FONT_ENV,
            font_search_list()
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )),
        _ => None,
    }
}
