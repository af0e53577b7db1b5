//! Spatial tiling of the VAE (diffusers' `enable_tiling`): inputs larger than a tile
//! are split into overlapping tiles, each encoded or decoded on its own, and the
//! outputs blended linearly.

use super::{AutoencoderKLCogVideoX, VaeConfig};
use crate::error::{Result, WorldModelError};
use tch::Tensor;

/// Spatial tiling parameters (diffusers' `tile_sample_min_*`, `tile_latent_min_*`,
/// `tile_overlap_factor_*`). Inputs larger than a tile in either direction are split
/// into overlapping tiles, each encoded/decoded on its own, and blended linearly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tiling {
    /// Tile height in pixels.
    pub tile_sample_min_height: i64,
    /// Tile width in pixels.
    pub tile_sample_min_width: i64,
    /// Tile height in latent pixels.
    pub tile_latent_min_height: i64,
    /// Tile width in latent pixels.
    pub tile_latent_min_width: i64,
    /// Fraction of a tile's height shared with the next tile.
    pub tile_overlap_factor_height: f64,
    /// Fraction of a tile's width shared with the next tile.
    pub tile_overlap_factor_width: f64,
}

/// Overrides for [`AutoencoderKLCogVideoX::enable_tiling`]; `None` keeps the current value.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TilingOptions {
    /// Tile height in pixels.
    pub tile_sample_min_height: Option<i64>,
    /// Tile width in pixels.
    pub tile_sample_min_width: Option<i64>,
    /// Fraction of a tile's height shared with the next tile, in `[0, 1)`.
    pub tile_overlap_factor_height: Option<f64>,
    /// Fraction of a tile's width shared with the next tile, in `[0, 1)`.
    pub tile_overlap_factor_width: Option<f64>,
}

/// Pixel tile -> latent tile: `int(sample / 2^(blocks - 1))` as in diffusers.
fn latent_tile(sample: i64, cfg: &VaeConfig) -> i64 {
    (sample as f64 / cfg.spatial_compression() as f64) as i64
}

impl Tiling {
    /// diffusers' defaults: half the config's sample size, overlaps 1/6 (height) and
    /// 1/5 (width).
    pub fn for_config(cfg: &VaeConfig) -> Self {
        let h = cfg.sample_height / 2;
        let w = cfg.sample_width / 2;
        Self {
            tile_sample_min_height: h,
            tile_sample_min_width: w,
            tile_latent_min_height: latent_tile(h, cfg),
            tile_latent_min_width: latent_tile(w, cfg),
            tile_overlap_factor_height: 1.0 / 6.0,
            tile_overlap_factor_width: 1.0 / 5.0,
        }
    }
}

/// A spatial tile's size in pixels, written `HxW` (`240x360`) in configs and
/// on the command line (`model.vae_tile`, `bench flow --tile`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct TileSize {
    /// Tile height in pixels.
    pub height_px: i64,
    /// Tile width in pixels.
    pub width_px: i64,
}

impl std::str::FromStr for TileSize {
    type Err = WorldModelError;

    fn from_str(text: &str) -> Result<Self> {
        let parsed = text.split_once('x').and_then(|(h, w)| {
            Some((h.trim().parse::<i64>().ok()?, w.trim().parse::<i64>().ok()?))
        });
        match parsed {
            Some((height_px, width_px)) if height_px > 0 && width_px > 0 => Ok(Self {
                height_px,
                width_px,
            }),
            _ => Err(WorldModelError::input(
                "tile",
                format!("{text:?}: expected HEIGHTxWIDTH in pixels, both positive, e.g. 240x360"),
            )),
        }
    }
}

impl std::fmt::Display for TileSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}x{}", self.height_px, self.width_px)
    }
}

impl TryFrom<String> for TileSize {
    type Error = WorldModelError;

    fn try_from(text: String) -> Result<Self> {
        text.parse()
    }
}

impl From<TileSize> for String {
    fn from(size: TileSize) -> Self {
        size.to_string()
    }
}

/// Which tiles the VAE runs in: the one rule of `predict`, training and the
/// Python model ([`AutoencoderKLCogVideoX::set_tiling`]). Written `auto`,
/// `off` or `HxW`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum VaeTiling {
    /// The VAE's own tiles for frames above [`super::TILING_MIN_PIXELS`]
    /// (memory; diffusers' CogVideoX examples tile above 256x256), whole
    /// frames below.
    #[default]
    Auto,
    /// Whole frames at any size.
    Off,
    /// Tiles of this size at any size of frame.
    Tiles(TileSize),
}

impl std::str::FromStr for VaeTiling {
    type Err = WorldModelError;

    fn from_str(text: &str) -> Result<Self> {
        match text.trim() {
            "auto" => Ok(Self::Auto),
            "off" => Ok(Self::Off),
            size => size.parse().map(Self::Tiles).map_err(|_| {
                WorldModelError::input(
                    "vae_tile",
                    format!(
                        "{text:?}: expected \"auto\" (the VAE's tiles above 256x256), \"off\" \
                         (whole frames) or HEIGHTxWIDTH in pixels, e.g. 144x200"
                    ),
                )
            }),
        }
    }
}

impl std::fmt::Display for VaeTiling {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Off => f.write_str("off"),
            Self::Tiles(size) => size.fmt(f),
        }
    }
}

impl AutoencoderKLCogVideoX {
    /// Tiles of `size` with the current overlaps ([`Self::enable_tiling`]),
    /// refused unless they join exactly ([`Self::tiles_join`]); `field`
    /// names the setting in the error. The tiling is unchanged on an error.
    pub fn enable_tiles(&mut self, size: TileSize, field: &str) -> Result<()> {
        let before = (self.tiling, self.use_tiling);
        self.enable_tiling(TilingOptions {
            tile_sample_min_height: Some(size.height_px),
            tile_sample_min_width: Some(size.width_px),
            ..TilingOptions::default()
        })
        .map_err(|e| match e {
            WorldModelError::Input { message, .. } => {
                WorldModelError::input(field, format!("{size} px: {message}"))
            }
            other => other,
        })?;
        if self.tiles_join() {
            return Ok(());
        }
        (self.tiling, self.use_tiling) = before;
        let s = self.cfg.spatial_compression();
        let t = Tiling::for_config(&self.cfg);
        Err(WorldModelError::input(
            field,
            format!(
                "{size} px: the tiles would not join exactly (their latent strides differ from \
                 the pixels each keeps, and the decoded video would come out larger than the \
                 input): expected tiles of a multiple of {s} px whose latent size (pixels / {s}) \
                 is a multiple of {} high and {} wide, as this VAE's default {}x{} (CogVideoX's: \
                 240x360, or 144x200 for a third of its pixels)",
                overlap_period(self.tiling.tile_overlap_factor_height),
                overlap_period(self.tiling.tile_overlap_factor_width),
                t.tile_sample_min_height,
                t.tile_sample_min_width
            ),
        ))
    }

    /// Tiles for frames of `height_px` x `width_px` as `tiling` says: the
    /// VAE's own tiles above [`super::TILING_MIN_PIXELS`] (`Auto`), whole
    /// frames (`Off`), or the given tiles ([`Self::enable_tiles`], refused
    /// unless they join; `field` names the setting in the error).
    pub fn set_tiling(
        &mut self,
        tiling: VaeTiling,
        (height_px, width_px): (usize, usize),
        field: &str,
    ) -> Result<()> {
        match tiling {
            VaeTiling::Tiles(size) => self.enable_tiles(size, field),
            VaeTiling::Auto if height_px * width_px > super::TILING_MIN_PIXELS => {
                self.tiling = Tiling::for_config(&self.cfg);
                self.enable_tiling(TilingOptions::default())
            }
            VaeTiling::Auto | VaeTiling::Off => {
                self.disable_tiling();
                Ok(())
            }
        }
    }

    /// Splits large inputs into overlapping spatial tiles (diffusers' `enable_tiling`);
    /// the options override the current tile sizes and overlaps.
    pub fn enable_tiling(&mut self, options: TilingOptions) -> Result<()> {
        let mut t = self.tiling;
        if let Some(h) = options.tile_sample_min_height {
            t.tile_sample_min_height = h;
        }
        if let Some(w) = options.tile_sample_min_width {
            t.tile_sample_min_width = w;
        }
        if let Some(f) = options.tile_overlap_factor_height {
            t.tile_overlap_factor_height = f;
        }
        if let Some(f) = options.tile_overlap_factor_width {
            t.tile_overlap_factor_width = f;
        }
        t.tile_latent_min_height = latent_tile(t.tile_sample_min_height, &self.cfg);
        t.tile_latent_min_width = latent_tile(t.tile_sample_min_width, &self.cfg);
        for (name, f) in [
            ("tile_overlap_factor_height", t.tile_overlap_factor_height),
            ("tile_overlap_factor_width", t.tile_overlap_factor_width),
        ] {
            if !(0.0..1.0).contains(&f) {
                return Err(WorldModelError::input(
                    name,
                    format!("{f}: must be in [0, 1)"),
                ));
            }
        }
        // The tile strides (overlap_*) of encode and decode must be positive.
        let strides = [
            (
                "tile_sample_min_height",
                t.tile_sample_min_height,
                t.tile_overlap_factor_height,
            ),
            (
                "tile_sample_min_width",
                t.tile_sample_min_width,
                t.tile_overlap_factor_width,
            ),
            (
                "tile_sample_min_height",
                t.tile_latent_min_height,
                t.tile_overlap_factor_height,
            ),
            (
                "tile_sample_min_width",
                t.tile_latent_min_width,
                t.tile_overlap_factor_width,
            ),
        ];
        for (name, size, factor) in strides {
            if tile_stride(size, factor) < 1 {
                return Err(WorldModelError::input(
                    name,
                    format!(
                        "tiles of {}x{} px ({}x{} latent) with overlaps {} / {} leave no stride: use larger tiles",
                        t.tile_sample_min_height,
                        t.tile_sample_min_width,
                        t.tile_latent_min_height,
                        t.tile_latent_min_width,
                        t.tile_overlap_factor_height,
                        t.tile_overlap_factor_width
                    ),
                ));
            }
        }
        self.tiling = t;
        self.use_tiling = true;
        Ok(())
    }

    /// Encodes/decodes whole frames (the default).
    pub fn disable_tiling(&mut self) {
        self.use_tiling = false;
    }

    /// The tiling parameters (used when tiling is enabled).
    pub fn tiling(&self) -> Tiling {
        self.tiling
    }

    /// Whether tiling is enabled.
    pub fn uses_tiling(&self) -> bool {
        self.use_tiling
    }

    /// diffusers' `tiled_encode`.
    pub(super) fn tiled_encode(&self, x: &Tensor) -> Result<Tensor> {
        let t = &self.tiling;
        let geometry = TileGeometry {
            tile_h: t.tile_sample_min_height,
            tile_w: t.tile_sample_min_width,
            stride_h: tile_stride(t.tile_sample_min_height, t.tile_overlap_factor_height),
            stride_w: tile_stride(t.tile_sample_min_width, t.tile_overlap_factor_width),
            blend_h: (t.tile_latent_min_height as f64 * t.tile_overlap_factor_height) as i64,
            blend_w: (t.tile_latent_min_width as f64 * t.tile_overlap_factor_width) as i64,
            out_tile_h: t.tile_latent_min_height,
            out_tile_w: t.tile_latent_min_width,
        };
        tiled(x, &geometry, |tile, _| self.encode_frames(tile))
    }

    /// diffusers' `tiled_decode`.
    pub(super) fn tiled_decode(&self, z: &Tensor) -> Result<Tensor> {
        tiled(z, &self.decode_geometry(), |tile, _| {
            self.decode_frames(tile)
        })
    }

    /// The tiles of [`Self::tiled_decode`].
    pub(super) fn decode_geometry(&self) -> TileGeometry {
        let t = &self.tiling;
        TileGeometry {
            tile_h: t.tile_latent_min_height,
            tile_w: t.tile_latent_min_width,
            stride_h: tile_stride(t.tile_latent_min_height, t.tile_overlap_factor_height),
            stride_w: tile_stride(t.tile_latent_min_width, t.tile_overlap_factor_width),
            blend_h: (t.tile_sample_min_height as f64 * t.tile_overlap_factor_height) as i64,
            blend_w: (t.tile_sample_min_width as f64 * t.tile_overlap_factor_width) as i64,
            out_tile_h: t.tile_sample_min_height,
            out_tile_w: t.tile_sample_min_width,
        }
    }

    /// Whether tiled decoding joins its tiles exactly: in both directions
    /// the latent stride between tiles, in pixels, equals the pixels each
    /// tile keeps (its size less the rows blended into the next). Otherwise
    /// the decoded video is larger than the latents' size in pixels, as
    /// with diffusers' `tiled_decode`; the default tiles (half the config's
    /// sample size, 240x360 for CogVideoX) join.
    pub fn tiles_join(&self) -> bool {
        let t = &self.tiling;
        let s = self.cfg.spatial_compression();
        [
            (
                t.tile_latent_min_height,
                t.tile_sample_min_height,
                t.tile_overlap_factor_height,
            ),
            (
                t.tile_latent_min_width,
                t.tile_sample_min_width,
                t.tile_overlap_factor_width,
            ),
        ]
        .into_iter()
        .all(|(latent, sample, overlap)| {
            tile_stride(latent, overlap) * s == sample - (sample as f64 * overlap) as i64
        })
    }

    /// Whether [`Self::decode`] tiles latents of this spatial size.
    pub(super) fn tiles_latents(&self, height: i64, width: i64) -> bool {
        self.use_tiling
            && (width > self.tiling.tile_latent_min_width
                || height > self.tiling.tile_latent_min_height)
    }
}

/// The smallest latent tile size whose overlap is a whole number of latent
/// pixels (6 for diffusers' 1/6, 5 for 1/5); 1 when there is none below 100.
fn overlap_period(overlap: f64) -> i64 {
    (1..100)
        .find(|&n| {
            let x = n as f64 * overlap;
            (x - x.round()).abs() < 1e-9
        })
        .unwrap_or(1)
}

/// `int(size * (1 - overlap))`: the step between tile origins.
fn tile_stride(size: i64, overlap: f64) -> i64 {
    (size as f64 * (1.0 - overlap)) as i64
}

/// Tile sizes of the input and output side of a tiled encode or decode.
pub(super) struct TileGeometry {
    /// Input tile size.
    tile_h: i64,
    tile_w: i64,
    /// Step between input tile origins.
    stride_h: i64,
    stride_w: i64,
    /// Output rows/columns blended with the previous tile.
    blend_h: i64,
    blend_w: i64,
    /// Nominal output tile size (the kept part is this minus the blend).
    out_tile_h: i64,
    out_tile_w: i64,
}

/// Runs `f` on overlapping tiles of `x [B, C, T, H, W]` (with each tile's
/// origin, row and column), blends each output tile with
/// its upper and left neighbours (already blended, as diffusers modifies its tiles in
/// place), keeps the first `out_tile - blend` rows/columns of each and concatenates.
pub(super) fn tiled(
    x: &Tensor,
    g: &TileGeometry,
    mut f: impl FnMut(&Tensor, (i64, i64)) -> Result<Tensor>,
) -> Result<Tensor> {
    let s = x.size();
    let (height, width) = (s[3], s[4]);
    let mut rows: Vec<Vec<Tensor>> = Vec::new();
    let mut i = 0;
    while i < height {
        let mut row = Vec::new();
        let mut j = 0;
        while j < width {
            // [B, C, T, <= tile_h, <= tile_w]
            let tile =
                x.narrow(3, i, g.tile_h.min(height - i))
                    .narrow(4, j, g.tile_w.min(width - j));
            row.push(f(&tile, (i, j))?);
            j += g.stride_w;
        }
        rows.push(row);
        i += g.stride_h;
    }
    let row_limit_h = g.out_tile_h - g.blend_h;
    let row_limit_w = g.out_tile_w - g.blend_w;
    let mut result_rows = Vec::with_capacity(rows.len());
    for i in 0..rows.len() {
        let mut result_row = Vec::with_capacity(rows[i].len());
        for j in 0..rows[i].len() {
            let mut tile = rows[i][j].shallow_clone();
            if i > 0 {
                tile = blend_v(&rows[i - 1][j], &tile, g.blend_h)?;
            }
            if j > 0 {
                tile = blend_h(&rows[i][j - 1], &tile, g.blend_w)?;
            }
            let ts = tile.size();
            result_row.push(tile.narrow(3, 0, row_limit_h.min(ts[3])).narrow(
                4,
                0,
                row_limit_w.min(ts[4]),
            ));
            rows[i][j] = tile;
        }
        result_rows.push(Tensor::f_cat(&result_row, 4)?);
    }
    Ok(Tensor::f_cat(&result_rows, 3)?)
}

/// Blends the last rows of `a` into the first rows of `b` along `dim`:
/// `b[y] = a[-e + y] * (1 - y / e) + b[y] * (y / e)` for `y < e`,
/// `e = min(a.len, b.len, extent)`; returns the blended copy of `b`.
fn blend(a: &Tensor, b: &Tensor, extent: i64, dim: i64) -> Result<Tensor> {
    let (la, lb) = (a.size()[dim as usize], b.size()[dim as usize]);
    let e = la.min(lb).min(extent);
    if e <= 0 {
        return Ok(b.shallow_clone());
    }
    let out = b.copy();
    for y in 0..e {
        let wb = y as f64 / e as f64;
        let row = a.narrow(dim, la - e + y, 1) * (1.0 - wb) + b.narrow(dim, y, 1) * wb;
        out.narrow(dim, y, 1).f_copy_(&row)?;
    }
    Ok(out)
}

/// diffusers' `blend_v` (height).
fn blend_v(a: &Tensor, b: &Tensor, extent: i64) -> Result<Tensor> {
    blend(a, b, extent, 3)
}

/// diffusers' `blend_h` (width).
fn blend_h(a: &Tensor, b: &Tensor, extent: i64) -> Result<Tensor> {
    blend(a, b, extent, 4)
}
