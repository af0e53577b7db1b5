//! Label maps alone ([`Rasterizer::render_labels`]): drawn into a reused
//! per-thread frame of packed keys, then copied where something was drawn.

use super::pixels::{Keys, BACKGROUND_KEY};
use super::{Rasterizer, RenderItem};
use std::cell::RefCell;

thread_local! {
    /// Frame buffers of [`Rasterizer::render_labels_into`].
    pub(super) static LABEL_FRAME: RefCell<LabelFrame> = const { RefCell::new(LabelFrame::new()) };
}

/// The per-thread frame of [`Rasterizer::render_labels_into`]: drawn into,
/// then its covered pixels are copied to the caller's label map, so that
/// map is only ever written (never read) and only where something is drawn:
/// for a freshly zeroed allocation, pages of background are never touched,
/// and none is first read (mapping the shared zero page) and then written
/// (a copy-on-write fault with a TLB flush on every core the process runs
/// on). Depth and label are packed per pixel ([`Keys`]). Between frames
/// every pixel is background ([`BACKGROUND_KEY`]), restored block by block
/// where something was drawn, so there is no full clear per frame.
#[derive(Debug)]
pub(super) struct LabelFrame {
    keys: Vec<u64>,
    /// Set while drawing: a frame left dirty (by a panic) is cleared in full.
    dirty: bool,
}

impl LabelFrame {
    pub(super) const fn new() -> Self {
        Self {
            keys: Vec::new(),
            dirty: false,
        }
    }
}

impl Rasterizer {
    /// [`Rasterizer::render_labels_into`] without distortion, drawing into
    /// the per-thread `frame` and then copying its covered pixels.
    pub(super) fn draw_labels(
        &self,
        items: &[RenderItem],
        frame: &mut LabelFrame,
        labels: &mut [u16],
    ) {
        let n = labels.len();
        if frame.dirty || frame.keys.len() != n {
            frame.keys.clear();
            frame.keys.resize(n, BACKGROUND_KEY);
        }
        frame.dirty = true;
        let pixels = Keys {
            keys: &mut frame.keys,
        };
        let drawn = self.draw_items(items, &self.pinhole, pixels);
        // Covered pixels are those with a label (items labelled 0 are not
        // drawn; the label is the key's low 16 bits), all inside `drawn`:
        // copy them and reset their blocks of each row to background.
        const BLOCK: usize = 16;
        let width = self.width as usize;
        for y in drawn.rows() {
            let row = y * width;
            let span = row + drawn.x0 as usize..row + drawn.x1 as usize + 1;
            let (Some(src), Some(dst)) = (frame.keys.get_mut(span.clone()), labels.get_mut(span))
            else {
                continue;
            };
            for (src, dst) in src.chunks_mut(BLOCK).zip(dst.chunks_mut(BLOCK)) {
                if src.iter().fold(0, |acc, &k| acc | k as u16) == 0 {
                    continue;
                }
                for (s, d) in src.iter().zip(dst.iter_mut()) {
                    let label = *s as u16;
                    if label != 0 {
                        *d = label;
                    }
                }
                src.fill(BACKGROUND_KEY);
            }
        }
        debug_assert!(
            frame.keys.iter().all(|&k| k == BACKGROUND_KEY),
            "drawn outside {drawn:?}"
        );
        frame.dirty = false;
    }
}
