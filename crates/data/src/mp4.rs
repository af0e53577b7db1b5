//! A minimal ISO-BMFF (MP4) muxer and demuxer for one H.264 video track.
//!
//! The muxer writes `ftyp`, `mdat` (length-prefixed NAL units, 4-byte
//! lengths) and `moov` with an `avc1` sample entry carrying `avcC` (SPS/PPS),
//! all samples in one chunk. The demuxer reads the first video track of any
//! MP4 (`stsd`, `stts`, `stsc`, `stsz`, `stco`/`co64`, `stss`); a sample
//! entry other than `avc1`/`avc3` (AV1 `av01`, HEVC, VP9, ...) is reported as
//! an unsupported codec.

use std::path::{Path, PathBuf};

/// MP4 container errors, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum Mp4Error {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// The file is not a well-formed MP4 (or is truncated).
    #[error("{path}: malformed MP4: {message}")]
    Malformed {
        /// File.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The video track uses a codec this crate cannot decode.
    #[error("{path}: unsupported codec \"{codec}\" (only H.264 avc1/avc3 is supported; re-encode the video to H.264)")]
    UnsupportedCodec {
        /// File.
        path: PathBuf,
        /// The sample entry's four-character code.
        codec: String,
    },
}

/// One coded sample of the track.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Byte offset in the file.
    pub offset: u64,
    /// Size in bytes.
    pub size: u32,
    /// Decode timestamp in track timescale units.
    pub dts: u64,
    /// Random access point.
    pub sync: bool,
}

/// The H.264 video track of an MP4 file.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoTrack {
    /// Coded width (pixels).
    pub width: u16,
    /// Coded height (pixels).
    pub height: u16,
    /// Media timescale (units per second).
    pub timescale: u32,
    /// Sequence parameter sets (NAL units without start codes).
    pub sps: Vec<Vec<u8>>,
    /// Picture parameter sets.
    pub pps: Vec<Vec<u8>>,
    /// NAL length field size (bytes).
    pub nal_length_size: u8,
    /// Samples in decode order.
    pub samples: Vec<Sample>,
}

// ---------------------------------------------------------------- muxer

fn put_box(out: &mut Vec<u8>, kind: &[u8; 4], body: &[u8]) {
    out.extend_from_slice(&((body.len() + 8) as u32).to_be_bytes());
    out.extend_from_slice(kind);
    out.extend_from_slice(body);
}

fn full_box(kind: &[u8; 4], version: u8, flags: u32, body: &[u8]) -> Vec<u8> {
    let mut b = Vec::with_capacity(body.len() + 4);
    b.push(version);
    b.extend_from_slice(&flags.to_be_bytes()[1..]);
    b.extend_from_slice(body);
    let mut out = Vec::new();
    put_box(&mut out, kind, &b);
    out
}

fn boxed(kind: &[u8; 4], body: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    put_box(&mut out, kind, body);
    out
}

const UNITY_MATRIX: [u32; 9] = [0x0001_0000, 0, 0, 0, 0x0001_0000, 0, 0, 0, 0x4000_0000];

/// An H.264 stream to mux.
#[derive(Debug, Clone, Copy)]
pub struct H264Stream<'a> {
    /// Width (pixels).
    pub width: u16,
    /// Height (pixels).
    pub height: u16,
    /// Media timescale (units per second).
    pub timescale: u32,
    /// Duration of every sample (timescale units).
    pub sample_duration: u32,
    /// Sequence parameter set (NAL unit without start code).
    pub sps: &'a [u8],
    /// Picture parameter set.
    pub pps: &'a [u8],
    /// Samples: length-prefixed (4-byte) NAL units.
    pub samples: &'a [Vec<u8>],
    /// `sync[i]`: sample `i` is an IDR picture.
    pub sync: &'a [bool],
}

/// Serialises an MP4 file holding `stream`.
pub fn mux_h264(stream: &H264Stream<'_>) -> Vec<u8> {
    let H264Stream {
        width,
        height,
        timescale,
        sample_duration: duration,
        sps,
        pps,
        samples,
        sync,
    } = *stream;
    let n = samples.len() as u32;
    let total = u64::from(n) * u64::from(duration);
    let mut out = Vec::new();
    let mut ftyp = Vec::new();
    ftyp.extend_from_slice(b"isom");
    ftyp.extend_from_slice(&512u32.to_be_bytes());
    for b in [b"isom", b"iso2", b"avc1", b"mp41"] {
        ftyp.extend_from_slice(b);
    }
    put_box(&mut out, b"ftyp", &ftyp);
    let data_len: u64 = samples.iter().map(|s| s.len() as u64).sum();
    if data_len + 8 <= u64::from(u32::MAX) {
        out.extend_from_slice(&((data_len + 8) as u32).to_be_bytes());
        out.extend_from_slice(b"mdat");
    } else {
        out.extend_from_slice(&1u32.to_be_bytes());
        out.extend_from_slice(b"mdat");
        out.extend_from_slice(&(data_len + 16).to_be_bytes());
    }
    let data_offset = out.len() as u64;
    for s in samples {
        out.extend_from_slice(s);
    }

    // moov
    let mut mvhd = Vec::new();
    mvhd.extend_from_slice(&[0; 8]); // creation, modification
    mvhd.extend_from_slice(&timescale.to_be_bytes());
    mvhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    mvhd.extend_from_slice(&0x0001_0000u32.to_be_bytes()); // rate 1.0
    mvhd.extend_from_slice(&0x0100u16.to_be_bytes()); // volume 1.0
    mvhd.extend_from_slice(&[0; 10]);
    for m in UNITY_MATRIX {
        mvhd.extend_from_slice(&m.to_be_bytes());
    }
    mvhd.extend_from_slice(&[0; 24]);
    mvhd.extend_from_slice(&2u32.to_be_bytes()); // next track id

    let mut tkhd = Vec::new();
    tkhd.extend_from_slice(&[0; 8]);
    tkhd.extend_from_slice(&1u32.to_be_bytes());
    tkhd.extend_from_slice(&[0; 4]);
    tkhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    tkhd.extend_from_slice(&[0; 8]);
    tkhd.extend_from_slice(&[0; 4]); // layer, alternate group
    tkhd.extend_from_slice(&[0; 4]); // volume, reserved
    for m in UNITY_MATRIX {
        tkhd.extend_from_slice(&m.to_be_bytes());
    }
    tkhd.extend_from_slice(&(u32::from(width) << 16).to_be_bytes());
    tkhd.extend_from_slice(&(u32::from(height) << 16).to_be_bytes());

    let mut mdhd = Vec::new();
    mdhd.extend_from_slice(&[0; 8]);
    mdhd.extend_from_slice(&timescale.to_be_bytes());
    mdhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    mdhd.extend_from_slice(&0x55C4u16.to_be_bytes()); // "und"
    mdhd.extend_from_slice(&[0; 2]);

    let mut hdlr = Vec::new();
    hdlr.extend_from_slice(&[0; 4]);
    hdlr.extend_from_slice(b"vide");
    hdlr.extend_from_slice(&[0; 12]);
    hdlr.extend_from_slice(b"VideoHandler\0");

    let mut avcc = vec![
        1,
        sps.get(1).copied().unwrap_or(66),
        sps.get(2).copied().unwrap_or(0),
        sps.get(3).copied().unwrap_or(30),
        0xFF,
        0xE1,
    ];
    avcc.extend_from_slice(&(sps.len() as u16).to_be_bytes());
    avcc.extend_from_slice(sps);
    avcc.push(1);
    avcc.extend_from_slice(&(pps.len() as u16).to_be_bytes());
    avcc.extend_from_slice(pps);

    let mut avc1 = Vec::new();
    avc1.extend_from_slice(&[0; 6]);
    avc1.extend_from_slice(&1u16.to_be_bytes());
    avc1.extend_from_slice(&[0; 16]);
    avc1.extend_from_slice(&width.to_be_bytes());
    avc1.extend_from_slice(&height.to_be_bytes());
    avc1.extend_from_slice(&0x0048_0000u32.to_be_bytes());
    avc1.extend_from_slice(&0x0048_0000u32.to_be_bytes());
    avc1.extend_from_slice(&[0; 4]);
    avc1.extend_from_slice(&1u16.to_be_bytes());
    avc1.extend_from_slice(&[0; 32]);
    avc1.extend_from_slice(&0x0018u16.to_be_bytes());
    avc1.extend_from_slice(&0xFFFFu16.to_be_bytes());
    avc1.extend_from_slice(&boxed(b"avcC", &avcc));

    let mut stsd = 1u32.to_be_bytes().to_vec();
    stsd.extend_from_slice(&boxed(b"avc1", &avc1));
    let mut stts = 1u32.to_be_bytes().to_vec();
    stts.extend_from_slice(&n.to_be_bytes());
    stts.extend_from_slice(&duration.to_be_bytes());
    let sync_ids: Vec<u32> = (0..n)
        .filter(|&i| sync.get(i as usize).copied().unwrap_or(false))
        .map(|i| i + 1)
        .collect();
    let mut stss = (sync_ids.len() as u32).to_be_bytes().to_vec();
    for i in &sync_ids {
        stss.extend_from_slice(&i.to_be_bytes());
    }
    let mut stsc = 1u32.to_be_bytes().to_vec();
    for v in [1u32, n, 1] {
        stsc.extend_from_slice(&v.to_be_bytes());
    }
    let mut stsz = 0u32.to_be_bytes().to_vec();
    stsz.extend_from_slice(&n.to_be_bytes());
    for s in samples {
        stsz.extend_from_slice(&(s.len() as u32).to_be_bytes());
    }
    let chunk_box = if data_offset <= u64::from(u32::MAX) {
        let mut b = 1u32.to_be_bytes().to_vec();
        b.extend_from_slice(&(data_offset as u32).to_be_bytes());
        full_box(b"stco", 0, 0, &b)
    } else {
        let mut b = 1u32.to_be_bytes().to_vec();
        b.extend_from_slice(&data_offset.to_be_bytes());
        full_box(b"co64", 0, 0, &b)
    };
    let mut stbl = Vec::new();
    stbl.extend_from_slice(&full_box(b"stsd", 0, 0, &stsd));
    stbl.extend_from_slice(&full_box(b"stts", 0, 0, &stts));
    stbl.extend_from_slice(&full_box(b"stss", 0, 0, &stss));
    stbl.extend_from_slice(&full_box(b"stsc", 0, 0, &stsc));
    stbl.extend_from_slice(&full_box(b"stsz", 0, 0, &stsz));
    stbl.extend_from_slice(&chunk_box);

    let mut dref = 1u32.to_be_bytes().to_vec();
    dref.extend_from_slice(&full_box(b"url ", 0, 1, &[]));
    let dinf = boxed(b"dinf", &full_box(b"dref", 0, 0, &dref));
    let mut minf = full_box(b"vmhd", 0, 1, &[0; 8]);
    minf.extend_from_slice(&dinf);
    minf.extend_from_slice(&boxed(b"stbl", &stbl));
    let mut mdia = full_box(b"mdhd", 0, 0, &mdhd);
    mdia.extend_from_slice(&full_box(b"hdlr", 0, 0, &hdlr));
    mdia.extend_from_slice(&boxed(b"minf", &minf));
    let mut trak = full_box(b"tkhd", 0, 3, &tkhd);
    trak.extend_from_slice(&boxed(b"mdia", &mdia));
    let mut moov = full_box(b"mvhd", 0, 0, &mvhd);
    moov.extend_from_slice(&boxed(b"trak", &trak));
    put_box(&mut out, b"moov", &moov);
    out
}

// ---------------------------------------------------------------- demuxer

/// Boxes of a container: `(four-character code, body)`.
type BoxList<'d> = Vec<([u8; 4], &'d [u8])>;

struct Reader<'a> {
    path: &'a Path,
}

impl Reader<'_> {
    fn err(&self, message: impl Into<String>) -> Mp4Error {
        Mp4Error::Malformed {
            path: self.path.to_path_buf(),
            message: message.into(),
        }
    }

    /// Splits `data` into `(kind, body)` boxes.
    fn boxes<'d>(&self, data: &'d [u8], ctx: &str) -> Result<BoxList<'d>, Mp4Error> {
        let mut out = Vec::new();
        let mut pos = 0usize;
        while pos < data.len() {
            if data.len() - pos < 8 {
                return Err(self.err(format!(
                    "{ctx}: {} trailing bytes are not a box header (truncated file?)",
                    data.len() - pos
                )));
            }
            let size32 =
                u32::from_be_bytes([data[pos], data[pos + 1], data[pos + 2], data[pos + 3]]);
            let kind = [data[pos + 4], data[pos + 5], data[pos + 6], data[pos + 7]];
            let (header, size) = match size32 {
                0 => (8usize, (data.len() - pos) as u64),
                1 => {
                    let b = data
                        .get(pos + 8..pos + 16)
                        .ok_or_else(|| self.err(format!("{ctx}: truncated large box header")))?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    (16usize, u64::from_be_bytes(a))
                }
                s => (8usize, u64::from(s)),
            };
            let end = (pos as u64)
                .checked_add(size)
                .filter(|&e| size >= header as u64 && e <= data.len() as u64);
            let Some(end) = end else {
                return Err(self.err(format!(
                    "{ctx}: box \"{}\" at byte {pos} claims {size} bytes but only {} remain (truncated file?)",
                    String::from_utf8_lossy(&kind),
                    data.len() - pos
                )));
            };
            out.push((kind, &data[pos + header..end as usize]));
            pos = end as usize;
        }
        Ok(out)
    }

    fn child<'d>(&self, data: &'d [u8], kind: &[u8; 4], ctx: &str) -> Result<&'d [u8], Mp4Error> {
        self.boxes(data, ctx)?
            .into_iter()
            .find(|(k, _)| k == kind)
            .map(|(_, b)| b)
            .ok_or_else(|| {
                self.err(format!(
                    "{ctx}: no \"{}\" box",
                    String::from_utf8_lossy(kind)
                ))
            })
    }
}

fn be_u32(b: &[u8], at: usize) -> Option<u32> {
    b.get(at..at + 4)
        .map(|s| u32::from_be_bytes([s[0], s[1], s[2], s[3]]))
}

fn be_u64(b: &[u8], at: usize) -> Option<u64> {
    b.get(at..at + 8).map(|s| {
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        u64::from_be_bytes(a)
    })
}

fn be_u16(b: &[u8], at: usize) -> Option<u16> {
    b.get(at..at + 2).map(|s| u16::from_be_bytes([s[0], s[1]]))
}

/// Reads the first video track's sample table from an MP4 file in memory.
pub fn demux(path: &Path, data: &[u8]) -> Result<VideoTrack, Mp4Error> {
    let r = Reader { path };
    let top = r.boxes(data, "file")?;
    if !top.iter().any(|(k, _)| k == b"ftyp") {
        return Err(r.err("no \"ftyp\" box: not an MP4 file"));
    }
    let moov = top
        .iter()
        .find(|(k, _)| k == b"moov")
        .map(|(_, b)| *b)
        .ok_or_else(|| r.err("no \"moov\" box (truncated or unfinished recording?)"))?;
    let short = |what: &str| r.err(format!("{what} is too short"));
    for (kind, trak) in r.boxes(moov, "moov")? {
        if &kind != b"trak" {
            continue;
        }
        let mdia = r.child(trak, b"mdia", "trak")?;
        let hdlr = r.child(mdia, b"hdlr", "mdia")?;
        if hdlr.get(8..12) != Some(b"vide".as_slice()) {
            continue;
        }
        let mdhd = r.child(mdia, b"mdhd", "mdia")?;
        let timescale = if mdhd.first() == Some(&1) {
            be_u32(mdhd, 20)
        } else {
            be_u32(mdhd, 12)
        }
        .ok_or_else(|| short("mdhd"))?;
        let minf = r.child(mdia, b"minf", "mdia")?;
        let stbl = r.child(minf, b"stbl", "minf")?;
        let stsd = r.child(stbl, b"stsd", "stbl")?;
        let entries = r.boxes(stsd.get(8..).ok_or_else(|| short("stsd"))?, "stsd")?;
        let (codec, entry) = entries
            .first()
            .ok_or_else(|| r.err("stsd has no sample entry"))?;
        if codec != b"avc1" && codec != b"avc3" {
            return Err(Mp4Error::UnsupportedCodec {
                path: path.to_path_buf(),
                codec: String::from_utf8_lossy(codec).into_owned(),
            });
        }
        let width = be_u16(entry, 24).ok_or_else(|| short("avc1 entry"))?;
        let height = be_u16(entry, 26).ok_or_else(|| short("avc1 entry"))?;
        let avcc = r.child(
            entry.get(78..).ok_or_else(|| short("avc1 entry"))?,
            b"avcC",
            "avc1",
        )?;
        let (sps, pps, nal_length_size) =
            parse_avcc(avcc).ok_or_else(|| r.err("malformed avcC"))?;

        let stsz = r.child(stbl, b"stsz", "stbl")?;
        let uniform = be_u32(stsz, 4).ok_or_else(|| short("stsz"))?;
        let count = be_u32(stsz, 8).ok_or_else(|| short("stsz"))? as usize;
        // Bounded by the file before anything is allocated: every sample
        // holds at least one byte of the file, and a table of sizes holds
        // four bytes per sample.
        let room = if uniform != 0 {
            data.len() / uniform as usize
        } else {
            stsz.len().saturating_sub(12) / 4
        };
        if count > room.min(data.len()) {
            return Err(r.err(format!(
                "stsz claims {count} samples, but {} (at most {}): corrupt sample table",
                if uniform != 0 {
                    format!("{uniform}-byte samples fit the {}-byte file", data.len())
                } else {
                    format!(
                        "its size table holds {} entries",
                        stsz.len().saturating_sub(12) / 4
                    )
                },
                room.min(data.len())
            )));
        }
        let sizes: Vec<u32> = if uniform != 0 {
            vec![uniform; count]
        } else {
            (0..count)
                .map(|i| be_u32(stsz, 12 + 4 * i).ok_or_else(|| short("stsz")))
                .collect::<Result<_, _>>()?
        };
        let chunk_offsets: Vec<u64> = if let Ok(stco) = r.child(stbl, b"stco", "stbl") {
            let n = be_u32(stco, 4).ok_or_else(|| short("stco"))? as usize;
            (0..n)
                .map(|i| {
                    be_u32(stco, 8 + 4 * i)
                        .map(u64::from)
                        .ok_or_else(|| short("stco"))
                })
                .collect::<Result<_, _>>()?
        } else {
            let co64 = r.child(stbl, b"co64", "stbl")?;
            let n = be_u32(co64, 4).ok_or_else(|| short("co64"))? as usize;
            (0..n)
                .map(|i| be_u64(co64, 8 + 8 * i).ok_or_else(|| short("co64")))
                .collect::<Result<_, _>>()?
        };
        let stsc = r.child(stbl, b"stsc", "stbl")?;
        let n_stsc = be_u32(stsc, 4).ok_or_else(|| short("stsc"))? as usize;
        let stsc_entries: Vec<(u32, u32)> = (0..n_stsc)
            .map(|i| Some((be_u32(stsc, 8 + 12 * i)?, be_u32(stsc, 12 + 12 * i)?)))
            .collect::<Option<_>>()
            .ok_or_else(|| short("stsc"))?;
        let stts = r.child(stbl, b"stts", "stbl")?;
        let n_stts = be_u32(stts, 4).ok_or_else(|| short("stts"))? as usize;
        let mut deltas = Vec::with_capacity(count);
        for i in 0..n_stts {
            let c = be_u32(stts, 8 + 8 * i).ok_or_else(|| short("stts"))?;
            let d = be_u32(stts, 12 + 8 * i).ok_or_else(|| short("stts"))?;
            let take = (c as usize).min(count - deltas.len());
            deltas.extend(std::iter::repeat_n(d, take));
        }
        let sync: Option<Vec<u32>> = match r.child(stbl, b"stss", "stbl") {
            Ok(stss) => {
                let n = be_u32(stss, 4).ok_or_else(|| short("stss"))? as usize;
                let mut s = (0..n)
                    .map(|i| be_u32(stss, 8 + 4 * i).ok_or_else(|| short("stss")))
                    .collect::<Result<Vec<_>, _>>()?;
                s.sort_unstable();
                Some(s)
            }
            Err(_) => None,
        };

        let mut samples = Vec::with_capacity(count);
        let mut dts = 0u64;
        for (c, &chunk_offset) in chunk_offsets.iter().enumerate() {
            let chunk = c as u32 + 1;
            let per = stsc_entries
                .iter()
                .rev()
                .find(|(first, _)| *first <= chunk)
                .map(|e| e.1)
                .unwrap_or(0);
            let mut off = chunk_offset;
            for _ in 0..per {
                let i = samples.len();
                if i >= count {
                    break;
                }
                let size = sizes[i];
                if off + u64::from(size) > data.len() as u64 {
                    return Err(r.err(format!(
                        "sample {i} (bytes {off}..{}) lies beyond the end of the file ({} bytes): truncated file",
                        off + u64::from(size),
                        data.len()
                    )));
                }
                samples.push(Sample {
                    offset: off,
                    size,
                    dts,
                    sync: sync
                        .as_ref()
                        .is_none_or(|s| s.binary_search(&(i as u32 + 1)).is_ok()),
                });
                dts += u64::from(deltas.get(i).copied().unwrap_or(0));
                off += u64::from(size);
            }
        }
        if samples.len() != count {
            return Err(r.err(format!(
                "sample table maps {} of {count} samples to chunks",
                samples.len()
            )));
        }
        return Ok(VideoTrack {
            width,
            height,
            timescale,
            sps,
            pps,
            nal_length_size,
            samples,
        });
    }
    Err(r.err("no video track"))
}

type ParamSets = (Vec<Vec<u8>>, Vec<Vec<u8>>, u8);

fn parse_avcc(b: &[u8]) -> Option<ParamSets> {
    let nal_length_size = (b.get(4)? & 3) + 1;
    let n_sps = (b.get(5)? & 0x1F) as usize;
    let mut pos = 6;
    let mut sps = Vec::new();
    for _ in 0..n_sps {
        let len = be_u16(b, pos)? as usize;
        sps.push(b.get(pos + 2..pos + 2 + len)?.to_vec());
        pos += 2 + len;
    }
    let n_pps = *b.get(pos)? as usize;
    pos += 1;
    let mut pps = Vec::new();
    for _ in 0..n_pps {
        let len = be_u16(b, pos)? as usize;
        pps.push(b.get(pos + 2..pos + 2 + len)?.to_vec());
        pos += 2 + len;
    }
    Some((sps, pps, nal_length_size))
}

/// Reads a file, mapping errors to [`Mp4Error::Io`].
pub fn read_file(path: &Path) -> Result<Vec<u8>, Mp4Error> {
    std::fs::read(path).map_err(|source| Mp4Error::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A 3-sample file (the sample bytes are not H.264: demuxing does not decode).
    fn small_file() -> Vec<u8> {
        let samples = vec![vec![0, 0, 0, 1, 0x65]; 3];
        mux_h264(&H264Stream {
            width: 16,
            height: 16,
            timescale: 30,
            sample_duration: 1,
            sps: &[0x67, 0x42, 0, 0x0a],
            pps: &[0x68, 0xce],
            samples: &samples,
            sync: &[true, false, false],
        })
    }

    /// The offset of the first field after `kind`'s version and flags.
    fn full_box_body(data: &[u8], kind: &[u8; 4]) -> usize {
        data.windows(4).position(|w| w == kind).unwrap() + 8
    }

    #[test]
    fn a_small_file_demuxes() {
        let t = demux(Path::new("ok.mp4"), &small_file()).unwrap();
        assert_eq!(t.samples.len(), 3);
        assert_eq!(t.samples[2].dts, 2);
        assert!(t.samples[0].sync && !t.samples[1].sync);
    }

    #[test]
    fn a_sample_count_beyond_the_file_is_an_error_not_an_allocation() {
        let mut data = small_file();
        let at = full_box_body(&data, b"stsz");
        data[at + 4..at + 8].copy_from_slice(&0xFFFF_FFF0u32.to_be_bytes());
        let e = demux(Path::new("lies.mp4"), &data).unwrap_err().to_string();
        assert!(
            e.contains("lies.mp4") && e.contains("4294967280 samples"),
            "{e}"
        );
        // The same with one uniform size for every sample.
        data[at..at + 4].copy_from_slice(&5u32.to_be_bytes());
        let e = demux(Path::new("lies.mp4"), &data).unwrap_err().to_string();
        assert!(e.contains("5-byte samples fit"), "{e}");
    }

    #[test]
    fn a_huge_time_to_sample_run_is_cut_at_the_sample_count() {
        let mut data = small_file();
        let at = full_box_body(&data, b"stts");
        // entry 0: (count, delta) after the entry count
        data[at + 4..at + 8].copy_from_slice(&u32::MAX.to_be_bytes());
        let t0 = std::time::Instant::now();
        let t = demux(Path::new("long.mp4"), &data).unwrap();
        assert_eq!(t.samples.len(), 3);
        assert_eq!(t.samples[2].dts, 2);
        assert!(t0.elapsed().as_secs_f64() < 1.0, "{:?}", t0.elapsed());
    }
}
