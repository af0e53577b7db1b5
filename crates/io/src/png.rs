//! PNG encoding of masks and images (the `png` crate, in memory).

/// Encodes an 8-bit grayscale image.
pub fn encode_gray8(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    encode(width, height, png::ColorType::Grayscale, pixels)
}

/// Encodes an 8-bit RGB image (`pixels` is `width * height * 3` bytes).
pub fn encode_rgb8(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    encode(width, height, png::ColorType::Rgb, pixels)
}

fn encode(width: u32, height: u32, color: png::ColorType, pixels: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(color);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Fast);
        // Writing into a Vec cannot fail except on a size mismatch, which is
        // a programming error; an empty Vec is returned then.
        let ok = enc
            .write_header()
            .and_then(|mut w| w.write_image_data(pixels).and_then(|()| w.finish()));
        if ok.is_err() {
            return Vec::new();
        }
    }
    out
}
