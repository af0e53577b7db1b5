//! Writes a PNG contact sheet of a LeRobot dataset's decoded video frames
//! (first, middle, last frame of the first episodes; masks tinted red).
//!
//! `cargo run -p bridgev2w-data --example contact_sheet -- DATASET OUT.png [EPISODES]`

use bridgev2w_data::lerobot::LeRobotDataset;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(root), Some(out)) = (args.get(1), args.get(2)) else {
        return Err("usage: contact_sheet DATASET OUT.png [EPISODES]".into());
    };
    let n: usize = args.get(3).map_or(Ok(4), |s| s.parse())?;
    let ds = LeRobotDataset::open(&PathBuf::from(root))?;
    let key = ds.video_keys.first().ok_or("no video key")?.clone();
    let shape = &ds.info["features"][&key]["shape"];
    let h = shape[0].as_u64().ok_or("bad shape")? as usize;
    let w = shape[1].as_u64().ok_or("bad shape")? as usize;
    let eps: Vec<i64> = ds
        .episodes
        .iter()
        .take(n)
        .map(|e| e.episode_index)
        .collect();
    let cols = 6;
    let (sw, sh) = (w * cols, h * eps.len());
    let mut sheet = vec![0u8; sw * sh * 3];
    for (row, &ep) in eps.iter().enumerate() {
        let frames = ds.read_video(ep, &key)?;
        let masks = ds.read_masks(ep).ok();
        let t = frames.len();
        let picks = [0, t / 2, t - 1];
        for (k, &f) in picks.iter().enumerate() {
            for (c, tint) in [(2 * k, false), (2 * k + 1, true)] {
                for y in 0..h {
                    for x in 0..w {
                        let src = (y * w + x) * 3;
                        let dst = ((row * h + y) * sw + c * w + x) * 3;
                        let mut px = [frames[f][src], frames[f][src + 1], frames[f][src + 2]];
                        if tint {
                            if let Some((_, m)) = &masks {
                                if m[f * w * h + y * w + x] != 0 {
                                    px = [255, px[1] / 2, px[2] / 2];
                                }
                            }
                        }
                        sheet[dst..dst + 3].copy_from_slice(&px);
                    }
                }
            }
        }
    }
    let png = bridgev2w_io::png::encode_rgb8(sw as u32, sh as u32, &sheet);
    std::fs::write(out, png)?;
    Ok(())
}
