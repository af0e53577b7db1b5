//! A minimal ISO-BMFF (MP4) muxer and demuxer for one video track.
//!
//! The muxer ([`mux_h264`]) writes `ftyp`, `mdat` (length-prefixed NAL
//! units, 4-byte lengths) and `moov` with an `avc1` sample entry carrying
//! `avcC` (SPS/PPS), all samples in one chunk. The demuxer ([`demux`]) reads
//! the first video track of any MP4 as encoders write it (`stsd`, `stts`,
//! `ctts` composition offsets, `stsc`, `stsz`, `stco`/`co64`, `stss`, and
//! the `edts`/`elst` edit list), H.264 (`avc1`/`avc3` with `avcC`) or AV1
//! (`av01` with `av1C`); another sample entry (HEVC, VP9, ...) is reported
//! as an unsupported codec. Fragmented files (`moof`) are not read.
//! [`demux_file`] reads the same from a file on disk holding only its
//! `moov` box in memory (the samples stay in the file, read by offset).

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
    /// The path is not a regular file of bounded size (a FIFO, a device, a
    /// folder, or larger than [`bridgev2w_io::confine::MAX_VIDEO_BYTES`]):
    /// refused before it is opened.
    #[error("{path}: {message}")]
    NotAFile {
        /// File.
        path: PathBuf,
        /// What it is instead.
        message: String,
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
    #[error("{path}: unsupported codec \"{codec}\" (H.264 avc1/avc3 and AV1 av01 are supported; re-encode the video, e.g. ffmpeg -c:v libx264)")]
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
    /// Presentation timestamp in track timescale units: `dts` plus the
    /// `ctts` composition offset, minus the edit list's start.
    pub pts: i64,
    /// Random access point.
    pub sync: bool,
}

/// H.264's decoder configuration (`avcC`).
#[derive(Debug, Clone, PartialEq)]
pub struct H264Config {
    /// `AVCProfileIndication` (66 Baseline, 77 Main, 100 High, ...).
    pub profile_idc: u8,
    /// Sequence parameter sets (NAL units without start codes).
    pub sps: Vec<Vec<u8>>,
    /// Picture parameter sets.
    pub pps: Vec<Vec<u8>>,
    /// NAL length field size (bytes).
    pub nal_length_size: u8,
}

/// AV1's decoder configuration (`av1C`).
#[derive(Debug, Clone, PartialEq)]
pub struct Av1Config {
    /// `seq_profile` (0 Main, 1 High, 2 Professional).
    pub seq_profile: u8,
    /// Bits per sample (8, 10, 12).
    pub bit_depth: u8,
    /// Monochrome (no chroma planes).
    pub monochrome: bool,
    /// The configuration OBUs (the sequence header), possibly empty.
    pub config_obus: Vec<u8>,
}

/// What a track's samples are coded with.
#[derive(Debug, Clone, PartialEq)]
pub enum TrackCodec {
    /// H.264 (`avc1`/`avc3`).
    H264(H264Config),
    /// AV1 (`av01`).
    Av1(Av1Config),
}

/// The video track of an MP4 file.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoTrack {
    /// Coded width (pixels).
    pub width: u16,
    /// Coded height (pixels).
    pub height: u16,
    /// Media timescale (units per second).
    pub timescale: u32,
    /// The codec and its configuration.
    pub codec: TrackCodec,
    /// Samples in decode order.
    pub samples: Vec<Sample>,
}

mod demux;
mod mux;

pub use demux::{demux, demux_file};
pub use mux::{mux_h264, H264Stream};

/// Checks, without opening it, that `path` is a regular file of at most
/// [`bridgev2w_io::confine::MAX_VIDEO_BYTES`]: opening a FIFO would block,
/// reading a device such as `/dev/zero` would never end.
pub fn check_video_file(path: &Path) -> Result<(), Mp4Error> {
    use bridgev2w_io::confine;
    confine::regular_file(path, confine::MAX_VIDEO_BYTES).map_err(|e| match e {
        confine::Refusal::Unresolved { path, source, .. } => Mp4Error::Io { path, source },
        e => Mp4Error::NotAFile {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    })
}

/// Reads a file ([`check_video_file`] first), mapping errors to [`Mp4Error::Io`].
pub fn read_file(path: &Path) -> Result<Vec<u8>, Mp4Error> {
    check_video_file(path)?;
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
