//! PNG encoding of masks and images (the `png` crate, in memory).

/// Encodes an 8-bit grayscale image.
pub fn encode_gray8(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    encode(
        width,
        height,
        png::ColorType::Grayscale,
        pixels,
        png::Compression::Fast,
    )
}

/// Encodes an 8-bit RGB image (`pixels` is `width * height * 3` bytes).
pub fn encode_rgb8(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    encode(
        width,
        height,
        png::ColorType::Rgb,
        pixels,
        png::Compression::Fast,
    )
}

/// [`encode_rgb8`] compressed harder (slower, files about half the size):
/// for images that are kept, such as the figures of the results.
pub fn encode_rgb8_small(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    encode(
        width,
        height,
        png::ColorType::Rgb,
        pixels,
        png::Compression::High,
    )
}

fn encode(
    width: u32,
    height: u32,
    color: png::ColorType,
    pixels: &[u8],
    compression: png::Compression,
) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(color);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(compression);
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

/// Decodes an 8-bit grayscale, RGB or RGBA PNG to `(width, height, RGB8
/// pixels)`; alpha is dropped. An error message for anything else.
pub fn decode_rgb8(bytes: &[u8]) -> Result<(u32, u32, Vec<u8>), String> {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .map_err(|e| e.to_string())?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| "the image is too large".to_string())?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    if info.bit_depth != png::BitDepth::Eight {
        return Err(format!("{:?} bits per sample, expected 8", info.bit_depth));
    }
    let px = &buf[..info.buffer_size()];
    let rgb = match info.color_type {
        png::ColorType::Rgb => px.to_vec(),
        png::ColorType::Rgba => px
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect(),
        png::ColorType::Grayscale => px.iter().flat_map(|&g| [g, g, g]).collect(),
        other => return Err(format!("colour type {other:?}, expected gray, RGB or RGBA")),
    };
    Ok((info.width, info.height, rgb))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn rgb_and_gray_round_trip() {
        let rgb: Vec<u8> = (0..2 * 3 * 3).map(|i| i as u8 * 10).collect();
        assert_eq!(
            decode_rgb8(&encode_rgb8(2, 3, &rgb)).unwrap(),
            (2, 3, rgb.clone())
        );
        assert_eq!(
            decode_rgb8(&encode_rgb8_small(2, 3, &rgb)).unwrap(),
            (2, 3, rgb)
        );
        let (w, h, px) = decode_rgb8(&encode_gray8(2, 1, &[7, 9])).unwrap();
        assert_eq!((w, h, px), (2, 1, vec![7, 7, 7, 9, 9, 9]));
        assert!(decode_rgb8(b"not a png").is_err());
    }
}
