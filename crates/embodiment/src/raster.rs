//! Triangle rasterizer: binary mask, per-link label map and depth.
