//! The demuxer: the first video track's sample table, codec configuration
//! and presentation times.

use super::{Av1Config, H264Config, Mp4Error, Sample, TrackCodec, VideoTrack};
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

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
    track_from_moov(&r, moov, data.len() as u64)
}

/// Reads the first video track's sample table from the MP4 file at `path`
/// without reading its media data: the top-level box headers are read by
/// seeking, and only `moov` is read whole. The same checks as [`demux`]
/// (every box and every sample within the file). The file must be a
/// regular file of bounded size ([`super::check_video_file`], checked before
/// it is opened).
pub fn demux_file(path: &Path) -> Result<VideoTrack, Mp4Error> {
    let io = |source: std::io::Error| Mp4Error::Io {
        path: path.to_path_buf(),
        source,
    };
    super::check_video_file(path)?;
    let r = Reader { path };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    let (mut ftyp, mut moov) = (false, None);
    let mut pos = 0u64;
    while pos < len {
        let left = len - pos;
        if left < 8 {
            return Err(r.err(format!(
                "file: {left} trailing bytes are not a box header (truncated file?)"
            )));
        }
        file.seek(SeekFrom::Start(pos)).map_err(io)?;
        let mut head = [0u8; 16];
        let header_len = if left >= 16 { 16 } else { 8 };
        file.read_exact(&mut head[..header_len]).map_err(io)?;
        let size32 = u32::from_be_bytes([head[0], head[1], head[2], head[3]]);
        let kind = [head[4], head[5], head[6], head[7]];
        let (header, size) = match size32 {
            0 => (8u64, left),
            1 => {
                if header_len < 16 {
                    return Err(r.err("file: truncated large box header"));
                }
                (16u64, be_u64(&head, 8).unwrap_or(0))
            }
            s => (8u64, u64::from(s)),
        };
        if size < header || size > left {
            return Err(r.err(format!(
                "file: box \"{}\" at byte {pos} claims {size} bytes but only {left} remain (truncated file?)",
                String::from_utf8_lossy(&kind),
            )));
        }
        if &kind == b"ftyp" {
            ftyp = true;
        } else if &kind == b"moov" && moov.is_none() {
            // Bounded by the file's length (checked above).
            let mut body = vec![0u8; (size - header) as usize];
            file.seek(SeekFrom::Start(pos + header)).map_err(io)?;
            file.read_exact(&mut body).map_err(io)?;
            moov = Some(body);
        }
        pos += size;
    }
    if !ftyp {
        return Err(r.err("no \"ftyp\" box: not an MP4 file"));
    }
    let moov = moov.ok_or_else(|| r.err("no \"moov\" box (truncated or unfinished recording?)"))?;
    track_from_moov(&r, &moov, len)
}

/// The first video track of `moov` in a file of `file_len` bytes.
fn track_from_moov(r: &Reader<'_>, moov: &[u8], file_len: u64) -> Result<VideoTrack, Mp4Error> {
    let path = r.path;
    let data_len = usize::try_from(file_len).unwrap_or(usize::MAX);
    let short = |what: &str| r.err(format!("{what} is too short"));
    let mvhd = r.child(moov, b"mvhd", "moov")?;
    let movie_timescale = if mvhd.first() == Some(&1) {
        be_u32(mvhd, 20)
    } else {
        be_u32(mvhd, 12)
    }
    .ok_or_else(|| short("mvhd"))?;
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
        let width = be_u16(entry, 24).ok_or_else(|| short("sample entry"))?;
        let height = be_u16(entry, 26).ok_or_else(|| short("sample entry"))?;
        // A VisualSampleEntry's boxes start after its 78 fixed bytes.
        let children = entry.get(78..).ok_or_else(|| short("sample entry"))?;
        let codec = match codec {
            b"avc1" | b"avc3" => {
                let avcc = r.child(children, b"avcC", "avc1")?;
                let (sps, pps, nal_length_size) =
                    parse_avcc(avcc).ok_or_else(|| r.err("malformed avcC"))?;
                TrackCodec::H264(H264Config {
                    profile_idc: avcc.get(1).copied().unwrap_or(0),
                    sps,
                    pps,
                    nal_length_size,
                })
            }
            b"av01" => {
                let av1c = r.child(children, b"av1C", "av01")?;
                TrackCodec::Av1(parse_av1c(av1c).ok_or_else(|| r.err("malformed av1C"))?)
            }
            other => {
                return Err(Mp4Error::UnsupportedCodec {
                    path: path.to_path_buf(),
                    codec: String::from_utf8_lossy(other).into_owned(),
                })
            }
        };

        let stsz = r.child(stbl, b"stsz", "stbl")?;
        let uniform = be_u32(stsz, 4).ok_or_else(|| short("stsz"))?;
        let count = be_u32(stsz, 8).ok_or_else(|| short("stsz"))? as usize;
        // Bounded by the file before anything is allocated: every sample
        // holds at least one byte of the file, and a table of sizes holds
        // four bytes per sample.
        let room = if uniform != 0 {
            data_len / uniform as usize
        } else {
            stsz.len().saturating_sub(12) / 4
        };
        if count > room.min(data_len) {
            return Err(r.err(format!(
                "stsz claims {count} samples, but {} (at most {}): corrupt sample table",
                if uniform != 0 {
                    format!("{uniform}-byte samples fit the {file_len}-byte file")
                } else {
                    format!(
                        "its size table holds {} entries",
                        stsz.len().saturating_sub(12) / 4
                    )
                },
                room.min(data_len)
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

        let offsets = composition_offsets(r, stbl, count)?;
        let start = edit_start(r, trak, movie_timescale, timescale)?;
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
                if off.saturating_add(u64::from(size)) > file_len {
                    return Err(r.err(format!(
                        "sample {i} (bytes {off}..{}) lies beyond the end of the file ({file_len} bytes): truncated file",
                        off.saturating_add(u64::from(size)),
                    )));
                }
                samples.push(Sample {
                    offset: off,
                    size,
                    dts,
                    pts: dts as i64 + offsets.get(i).copied().unwrap_or(0) - start,
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
            codec,
            samples,
        });
    }
    Err(r.err("no video track"))
}

/// Each sample's composition offset (`ctts`; zero without one), in decode
/// order: presentation = decode time + offset. Version 1 offsets are signed.
fn composition_offsets(r: &Reader<'_>, stbl: &[u8], count: usize) -> Result<Vec<i64>, Mp4Error> {
    let Ok(ctts) = r.child(stbl, b"ctts", "stbl") else {
        return Ok(vec![0; count]);
    };
    let short = || r.err("ctts is too short");
    let signed = ctts.first() == Some(&1);
    let n = be_u32(ctts, 4).ok_or_else(short)? as usize;
    let mut out = Vec::with_capacity(count);
    for e in 0..n {
        let c = be_u32(ctts, 8 + 8 * e).ok_or_else(short)? as usize;
        let raw = be_u32(ctts, 12 + 8 * e).ok_or_else(short)?;
        let off = if signed {
            i64::from(raw as i32)
        } else {
            i64::from(raw)
        };
        let take = c.min(count - out.len());
        out.extend(std::iter::repeat_n(off, take));
        if out.len() == count {
            break;
        }
    }
    out.resize(count, 0);
    Ok(out)
}

/// The media time (track timescale) shown at presentation time 0 by the
/// track's edit list (`edts`/`elst`): the first edit's `media_time`, less
/// the leading empty edits' delay; 0 without an edit list.
fn edit_start(
    r: &Reader<'_>,
    trak: &[u8],
    movie_timescale: u32,
    timescale: u32,
) -> Result<i64, Mp4Error> {
    let Ok(edts) = r.child(trak, b"edts", "trak") else {
        return Ok(0);
    };
    let Ok(elst) = r.child(edts, b"elst", "edts") else {
        return Ok(0);
    };
    let short = || r.err("elst is too short");
    let v1 = elst.first() == Some(&1);
    let n = be_u32(elst, 4).ok_or_else(short)? as usize;
    let mut delay_movie = 0i64;
    for e in 0..n {
        let (duration, media_time) = if v1 {
            let at = 8 + 20 * e;
            (
                be_u64(elst, at).ok_or_else(short)? as i64,
                be_u64(elst, at + 8).ok_or_else(short)? as i64,
            )
        } else {
            let at = 8 + 12 * e;
            (
                i64::from(be_u32(elst, at).ok_or_else(short)?),
                i64::from(be_u32(elst, at + 4).ok_or_else(short)? as i32),
            )
        };
        if media_time == -1 {
            delay_movie = delay_movie.saturating_add(duration); // an empty edit
            continue;
        }
        let delay = if movie_timescale == 0 {
            0
        } else {
            delay_movie.saturating_mul(i64::from(timescale)) / i64::from(movie_timescale)
        };
        return Ok(media_time - delay);
    }
    Ok(0)
}

/// `av1C`: marker and version, then `seq_profile`, `seq_level_idx_0`, the
/// tier, bit-depth and chroma flags, a byte of presentation delay, then the
/// configuration OBUs.
fn parse_av1c(b: &[u8]) -> Option<Av1Config> {
    if b.first()? & 0x80 == 0 {
        return None; // marker bit
    }
    let seq_profile = b.get(1)? >> 5;
    let flags = *b.get(2)?;
    let high_bitdepth = flags & 0x40 != 0;
    let twelve_bit = flags & 0x20 != 0;
    Some(Av1Config {
        seq_profile,
        bit_depth: match (high_bitdepth, twelve_bit) {
            (false, _) => 8,
            (true, false) => 10,
            (true, true) => 12,
        },
        monochrome: flags & 0x10 != 0,
        config_obus: b.get(4..)?.to_vec(),
    })
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
