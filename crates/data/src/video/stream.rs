//! Decoding as a stream: a video's frame count, size and presentation times
//! are known up front (from the demuxed sample table), and its frames come
//! one at a time, in presentation order, as RGB8. Samples are read from the
//! file by offset (seek and read) as they are decoded; only the `moov` box
//! is read whole. The memory held is the codec's (its reference and reorder
//! buffers) plus the few decoded frames waiting to be returned (at most the
//! pictures the decoder still holds when it is flushed at the end: the
//! reorder depth), never the video's length.

use super::av1::Av1Decoder;
use super::h264::H264Decoder;
use super::{DecodedVideo, VideoError};
use crate::mp4::{demux_file, Mp4Error, Sample, TrackCodec, VideoTrack};
use std::collections::VecDeque;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::iter::FusedIterator;
use std::path::{Path, PathBuf};

/// What is known of a video before it is decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoInfo {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Frames (the track's samples).
    pub frames: usize,
    /// Each frame's presentation time (seconds), in presentation order.
    pub timestamps_s: Vec<f64>,
    /// "H.264" or "AV1".
    pub codec: &'static str,
}

impl VideoInfo {
    /// Bytes of one RGB8 frame (`height * width * 3`).
    pub fn frame_bytes(&self) -> usize {
        self.width * self.height * 3
    }

    /// How many frames at the start the track's edit list (`elst`) hides:
    /// the demuxer shifts presentation times so that the first edit's
    /// media time is 0, and a frame is hidden when it ends (the next frame
    /// starts) at or before 0; the last frame, when it starts before 0. A
    /// player shows none of them; 0 without an edit list that cuts frames.
    pub fn hidden_by_edit_list(&self) -> usize {
        let ts = &self.timestamps_s;
        (0..ts.len())
            .take_while(|&i| ts.get(i + 1).map_or(ts[i] < 0.0, |&next| next <= 0.0))
            .count()
    }
}

/// One decoded frame.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoFrame {
    /// Index in presentation order (0-based).
    pub index: usize,
    /// Presentation time (seconds).
    pub timestamp_s: f64,
    /// Interleaved RGB8, `height * width * 3` bytes.
    pub rgb: Vec<u8>,
}

enum Codec {
    H264(H264Decoder),
    Av1(Av1Decoder),
}

/// A video decoded frame by frame (an iterator of
/// `Result<VideoFrame, VideoError>`, in presentation order; it ends after
/// the last frame or after the first error).
///
/// ```no_run
/// # fn main() -> Result<(), bridgev2w_data::video::VideoError> {
/// use bridgev2w_data::video::VideoStream;
/// let mut video = VideoStream::open(std::path::Path::new("0.mp4"))?;
/// println!("{} frames of {}x{}", video.info().frames, video.info().width, video.info().height);
/// while let Some(frame) = video.next_frame()? {
///     println!("frame {} at {} s: {} bytes", frame.index, frame.timestamp_s, frame.rgb.len());
/// }
/// # Ok(())
/// # }
/// ```
pub struct VideoStream<R = File> {
    path: PathBuf,
    reader: R,
    /// Where `reader` stands, when known (saves a seek between contiguous samples).
    position: Option<u64>,
    samples: Vec<Sample>,
    info: VideoInfo,
    codec: Codec,
    /// The next sample to decode (decode order).
    next_sample: usize,
    /// Frames returned so far.
    emitted: usize,
    /// Decoded frames not yet returned.
    ready: VecDeque<Vec<u8>>,
    /// The most frames `ready` has held at once.
    peak_ready: usize,
    /// The decoder was flushed after the last sample.
    flushed: bool,
    /// The last frame or an error was returned.
    done: bool,
    /// The sample being read (reused for H.264).
    buf: Vec<u8>,
}

impl<R> std::fmt::Debug for VideoStream<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoStream")
            .field("path", &self.path)
            .field("info", &self.info)
            .field("emitted", &self.emitted)
            .finish()
    }
}

impl VideoStream<File> {
    /// Opens the MP4 file at `path` (H.264 or AV1): its sample table is read
    /// (the `moov` box), its samples are not.
    pub fn open(path: &Path) -> Result<Self, VideoError> {
        let track = demux_file(path)?;
        let file = File::open(path).map_err(|source| Mp4Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::new(path, file, track)
    }
}

impl<R: Read + Seek> VideoStream<R> {
    /// Decodes `track`, whose samples `reader` holds at the track's offsets
    /// (the file itself, or e.g. a `Cursor` over its bytes); `path` names
    /// the video in errors. An unsupported profile is an error here.
    pub fn new(path: &Path, reader: R, track: VideoTrack) -> Result<Self, VideoError> {
        let mut ready = VecDeque::new();
        let codec = match &track.codec {
            TrackCodec::H264(config) => Codec::H264(H264Decoder::new(path, &track, config)?),
            TrackCodec::Av1(config) => {
                Codec::Av1(Av1Decoder::new(path, &track, config, &mut ready)?)
            }
        };
        // Decoders return frames in presentation order.
        let mut pts: Vec<i64> = track.samples.iter().map(|s| s.pts).collect();
        pts.sort_unstable();
        let timescale = f64::from(track.timescale.max(1));
        let info = VideoInfo {
            width: usize::from(track.width),
            height: usize::from(track.height),
            frames: track.samples.len(),
            timestamps_s: pts.iter().map(|&p| p as f64 / timescale).collect(),
            codec: super::codec_name(&track.codec),
        };
        Ok(Self {
            path: path.to_path_buf(),
            reader,
            position: None,
            samples: track.samples,
            info,
            codec,
            next_sample: 0,
            emitted: 0,
            peak_ready: ready.len(),
            ready,
            flushed: false,
            done: false,
            buf: Vec::new(),
        })
    }

    /// Size, frame count, timestamps and codec.
    pub fn info(&self) -> &VideoInfo {
        &self.info
    }

    /// The file (for messages).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Frames returned so far.
    pub fn frames_read(&self) -> usize {
        self.emitted
    }

    /// The most decoded frames held at once, waiting to be returned (the
    /// decoder's own reference pictures not counted).
    pub fn peak_frames_held(&self) -> usize {
        self.peak_ready
    }

    /// The next frame in presentation order; `None` after the last one.
    /// After an error the stream is over (`None` from then on).
    pub fn next_frame(&mut self) -> Result<Option<VideoFrame>, VideoError> {
        if self.done {
            return Ok(None);
        }
        match self.advance() {
            Ok(frame) => {
                self.done = frame.is_none();
                Ok(frame)
            }
            Err(e) => {
                self.done = true;
                self.ready.clear();
                Err(e)
            }
        }
    }

    /// Decodes the remaining frames into memory (what [`super::decode_mp4`]
    /// returns: the whole video, so `frames * height * width * 3` bytes).
    pub fn read_all(mut self) -> Result<DecodedVideo, VideoError> {
        let mut frames = Vec::with_capacity(self.info.frames - self.emitted);
        while let Some(frame) = self.next_frame()? {
            frames.push(frame.rgb);
        }
        Ok(DecodedVideo {
            width: self.info.width,
            height: self.info.height,
            frames,
            timestamps_s: self.info.timestamps_s,
        })
    }

    fn advance(&mut self) -> Result<Option<VideoFrame>, VideoError> {
        let n = self.samples.len();
        loop {
            if let Some(rgb) = self.ready.pop_front() {
                let index = self.emitted;
                let Some(&timestamp_s) = self.info.timestamps_s.get(index) else {
                    return Err(self.count_err(index + 1 + self.ready.len()));
                };
                self.emitted += 1;
                return Ok(Some(VideoFrame {
                    index,
                    timestamp_s,
                    rgb,
                }));
            }
            if self.next_sample < n {
                let i = self.next_sample;
                self.next_sample += 1;
                let sync = self.samples[i].sync;
                self.read_sample(i)?;
                match &mut self.codec {
                    Codec::H264(d) => d.feed(i, &self.buf, sync, &mut self.ready)?,
                    Codec::Av1(d) => d.feed(i, std::mem::take(&mut self.buf), &mut self.ready)?,
                }
            } else if !self.flushed {
                self.flushed = true;
                match &mut self.codec {
                    Codec::H264(d) => d.finish(n, &mut self.ready)?,
                    Codec::Av1(d) => d.finish(n, &mut self.ready)?,
                }
            } else if self.emitted != n {
                return Err(self.count_err(self.emitted));
            } else {
                return Ok(None);
            }
            self.peak_ready = self.peak_ready.max(self.ready.len());
        }
    }

    /// The decoder gave `decoded` frames for the track's samples.
    fn count_err(&self, decoded: usize) -> VideoError {
        VideoError::Codec {
            path: self.path.clone(),
            codec: self.info.codec,
            op: "decode",
            frame: decoded.min(self.emitted),
            message: format!(
                "decoded {decoded} frames from {} samples",
                self.samples.len()
            ),
        }
    }

    /// Reads sample `i` into `buf`.
    fn read_sample(&mut self, i: usize) -> Result<(), VideoError> {
        let s = &self.samples[i];
        let (offset, size) = (s.offset, s.size as usize);
        let fail = |e: std::io::Error| VideoError::Frame {
            path: self.path.clone(),
            message: format!(
                "cannot read sample {i} (bytes {offset}..{}): {e}",
                offset + size as u64
            ),
        };
        if self.position != Some(offset) {
            self.reader.seek(SeekFrom::Start(offset)).map_err(fail)?;
        }
        self.position = None;
        self.buf.clear();
        self.buf.resize(size, 0);
        self.reader.read_exact(&mut self.buf).map_err(fail)?;
        self.position = Some(offset + size as u64);
        Ok(())
    }
}

impl<R: Read + Seek> Iterator for VideoStream<R> {
    type Item = Result<VideoFrame, VideoError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_frame().transpose()
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = if self.done {
            0
        } else {
            self.info.frames - self.emitted
        };
        // One more item where the decoder's frame count disagrees (an error).
        (0, Some(left.saturating_add(1)))
    }
}

impl<R: Read + Seek> FusedIterator for VideoStream<R> {}
