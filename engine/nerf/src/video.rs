//! Videos that a browser plays: H.264 (OpenH264, built from source) in an MP4 container (the
//! `mp4` crate), written frame by frame as they are rendered; and read back (frame count,
//! size, frame rate, decoded frames) for tests and checks.
//!
//! H.264's 4:2:0 chroma needs even sizes: a frame of odd width or height is encoded with its
//! last column or row repeated (the video is then a pixel wider or higher than the frames).
//! The file is written as `NAME.partial` and renamed when finished, so a video that is there
//! is whole.

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use mp4::{
    AvcConfig, FourCC, MediaConfig, Mp4Config, Mp4Sample, Mp4Writer, TrackConfig, TrackType,
};
use openh264::encoder::{Encoder, EncoderConfig, FrameRate, FrameType, RateControlMode};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use openh264::OpenH264API;

/// Why a video could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    /// The file could not be created, written or read.
    #[error("{path}: {error}")]
    Io {
        /// The video file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// The encoder, the decoder or the container refused, or a frame does not fit the video.
    #[error("{path}: {problem}")]
    Codec {
        /// The video file.
        path: PathBuf,
        /// What went wrong.
        problem: String,
    },
}

/// The media timescale: ticks per second of the video track.
const TIMESCALE: u32 = 90_000;

/// An MP4 file being written, one frame at a time.
pub struct VideoWriter {
    /// The finished file's path, and the one written until then.
    path: PathBuf,
    partial: PathBuf,
    encoder: Encoder,
    mp4: Option<Mp4Writer<BufWriter<std::fs::File>>>,
    /// The frames' size, and the encoded (even) size.
    size: (u32, u32),
    even: (u32, u32),
    /// Ticks per frame.
    duration: u32,
    frames: u64,
    rgb8: Vec<u8>,
}

impl std::fmt::Debug for VideoWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoWriter")
            .field("path", &self.path)
            .field("size", &self.size)
            .field("frames", &self.frames)
            .finish_non_exhaustive()
    }
}

/// The H.264 NAL units of an Annex-B stream (start codes removed).
fn nal_units(annex_b: &[u8]) -> Vec<&[u8]> {
    openh264::nal_units(annex_b)
        .map(|n| {
            let skip = n.iter().take_while(|&&b| b == 0).count();
            &n[(skip + 1).min(n.len())..]
        })
        .filter(|n| !n.is_empty())
        .collect()
}

impl VideoWriter {
    /// Starts `path` for frames of `width` x `height` at `fps` frames per second.
    pub fn create(path: &Path, width: u32, height: u32, fps: f64) -> Result<Self, VideoError> {
        let codec = |p: String| VideoError::Codec {
            path: path.to_path_buf(),
            problem: p,
        };
        if width == 0 || height == 0 || width > 4096 || height > 4096 {
            return Err(codec(format!(
                "{width}x{height}: frames of 1 to 4096 pixels a side"
            )));
        }
        if !(fps.is_finite() && fps > 0.0 && fps <= 1000.0) {
            return Err(codec(format!("{fps} frames per second: use (0, 1000]")));
        }
        let even = (width + width % 2, height + height % 2);
        // A fixed quantiser (no rate control) and every frame kept (no skipping to meet a
        // rate), so frame k of the video is frame k of the path at an even quality.
        let config = EncoderConfig::new()
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .rate_control_mode(RateControlMode::Off)
            .skip_frames(false);
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| codec(format!("the H.264 encoder: {e}")))?;
        let mut name = path.file_name().unwrap_or_default().to_os_string();
        name.push(".partial");
        let partial = path.with_file_name(name);
        let file = std::fs::File::create(&partial).map_err(|e| VideoError::Io {
            path: partial.clone(),
            error: e,
        })?;
        let mp4 = Mp4Writer::write_start(
            BufWriter::new(file),
            &Mp4Config {
                major_brand: FourCC::from(*b"isom"),
                minor_version: 512,
                compatible_brands: vec![
                    FourCC::from(*b"isom"),
                    FourCC::from(*b"iso2"),
                    FourCC::from(*b"avc1"),
                    FourCC::from(*b"mp41"),
                ],
                timescale: 1000,
            },
        )
        .map_err(|e| codec(format!("the MP4 container: {e}")))?;
        Ok(VideoWriter {
            path: path.to_path_buf(),
            partial,
            encoder,
            mp4: Some(mp4),
            size: (width, height),
            even,
            duration: (TIMESCALE as f64 / fps).round().max(1.0) as u32,
            frames: 0,
            rgb8: Vec::new(),
        })
    }

    fn codec(&self, problem: String) -> VideoError {
        VideoError::Codec {
            path: self.path.clone(),
            problem,
        }
    }

    /// Encodes one frame: linear RGB in [0, 1] as `write_png` takes it, row-major, the size
    /// the video was created with.
    pub fn push(&mut self, rgb: &[f32]) -> Result<(), VideoError> {
        let (w, h) = (self.size.0 as usize, self.size.1 as usize);
        if rgb.len() != w * h * 3 {
            return Err(self.codec(format!(
                "frame {} holds {} values, a {w}x{h} RGB frame {}",
                self.frames,
                rgb.len(),
                w * h * 3
            )));
        }
        let (ew, eh) = (self.even.0 as usize, self.even.1 as usize);
        self.rgb8.clear();
        self.rgb8.reserve(ew * eh * 3);
        for y in 0..eh {
            let sy = y.min(h - 1);
            for x in 0..ew {
                let sx = x.min(w - 1);
                for c in 0..3 {
                    let v = rgb[(sy * w + sx) * 3 + c];
                    self.rgb8.push((v.clamp(0.0, 1.0) * 255.0).round() as u8);
                }
            }
        }
        let yuv = YUVBuffer::from_rgb_source(RgbSliceU8::new(&self.rgb8, (ew, eh)));
        let stream = self.encoder.encode(&yuv).map_err(|e| VideoError::Codec {
            path: self.path.clone(),
            problem: format!("encoding frame {}: {e}", self.frames),
        })?;
        let sync = matches!(stream.frame_type(), FrameType::IDR | FrameType::I);
        let annex_b = stream.to_vec();
        let mut sps = None;
        let mut pps = None;
        let mut sample = Vec::new();
        for nal in nal_units(&annex_b) {
            match nal[0] & 0x1f {
                7 => sps = Some(nal.to_vec()),
                8 => pps = Some(nal.to_vec()),
                _ => {
                    sample.extend((nal.len() as u32).to_be_bytes());
                    sample.extend_from_slice(nal);
                }
            }
        }
        let path = self.path.clone();
        let Some(mp4) = self.mp4.as_mut() else {
            return Err(self.codec("the video is already finished".into()));
        };
        if self.frames == 0 {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err(VideoError::Codec {
                    path,
                    problem: "the encoder's first frame carries no SPS and PPS".into(),
                });
            };
            mp4.add_track(&TrackConfig {
                track_type: TrackType::Video,
                timescale: TIMESCALE,
                language: "und".into(),
                media_conf: MediaConfig::AvcConfig(AvcConfig {
                    width: self.even.0 as u16,
                    height: self.even.1 as u16,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            })
            .map_err(|e| VideoError::Codec {
                path: path.clone(),
                problem: format!("the MP4 track: {e}"),
            })?;
        }
        if sample.is_empty() {
            return Err(VideoError::Codec {
                path,
                problem: format!("the encoder skipped frame {}", self.frames),
            });
        }
        mp4.write_sample(
            1,
            &Mp4Sample {
                start_time: self.frames * self.duration as u64,
                duration: self.duration,
                rendering_offset: 0,
                is_sync: sync,
                bytes: sample.into(),
            },
        )
        .map_err(|e| VideoError::Codec {
            path,
            problem: format!("writing frame {}: {e}", self.frames),
        })?;
        self.frames += 1;
        Ok(())
    }

    /// Finishes the file (its index), returning the frames written.
    pub fn finish(mut self) -> Result<u64, VideoError> {
        let path = self.path.clone();
        let Some(mut mp4) = self.mp4.take() else {
            return Err(self.codec("the video is already finished".into()));
        };
        if self.frames == 0 {
            return Err(self.codec("no frame was written".into()));
        }
        mp4.write_end().map_err(|e| VideoError::Codec {
            path: path.clone(),
            problem: format!("finishing the MP4: {e}"),
        })?;
        let mut w = mp4.into_writer();
        w.flush()
            .and_then(|_| w.get_mut().sync_all())
            .and_then(|_| std::fs::rename(&self.partial, &path))
            .and_then(|_| {
                extranerf_gpu::files::sync_dir(
                    path.parent()
                        .filter(|p| !p.as_os_str().is_empty())
                        .unwrap_or(Path::new(".")),
                )
            })
            .map_err(|e| VideoError::Io { path, error: e })?;
        Ok(self.frames)
    }
}

/// What a video file holds: its frames decoded as 8-bit RGB, its size and its frame rate.
#[derive(Clone, Debug, PartialEq)]
pub struct DecodedVideo {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frames per second (the track's timescale over its first sample's duration).
    pub fps: f64,
    /// Each frame, RGB row-major.
    pub frames: Vec<Vec<u8>>,
}

/// Reads and decodes the H.264 track of the MP4 file at `path`.
pub fn read_video(path: &Path) -> Result<DecodedVideo, VideoError> {
    let codec = |p: String| VideoError::Codec {
        path: path.to_path_buf(),
        problem: p,
    };
    let bytes = std::fs::read(path).map_err(|e| VideoError::Io {
        path: path.to_path_buf(),
        error: e,
    })?;
    let size = bytes.len() as u64;
    let mut mp4 = mp4::Mp4Reader::read_header(std::io::Cursor::new(bytes), size)
        .map_err(|e| codec(format!("not an MP4 file: {e}")))?;
    let (id, width, height, timescale, sps, pps) = {
        let (id, track) = mp4
            .tracks()
            .iter()
            .find(|(_, t)| t.track_type().ok() == Some(TrackType::Video))
            .ok_or_else(|| codec("no video track".into()))?;
        let params = |r: mp4::Result<&[u8]>| {
            r.map(<[u8]>::to_vec)
                .map_err(|e| codec(format!("no H.264 parameters: {e}")))
        };
        (
            *id,
            u32::from(track.width()),
            u32::from(track.height()),
            track.timescale(),
            params(track.sequence_parameter_set())?,
            params(track.picture_parameter_set())?,
        )
    };
    let count = mp4
        .sample_count(id)
        .map_err(|e| codec(format!("the sample table: {e}")))?;
    let mut decoder = openh264::decoder::Decoder::with_api_config(
        OpenH264API::from_source(),
        openh264::decoder::DecoderConfig::new(),
    )
    .map_err(|e| codec(format!("the H.264 decoder: {e}")))?;
    let mut frames = Vec::new();
    let mut fps = 0.0;
    let annex = |nal: &[u8]| [&[0u8, 0, 0, 1][..], nal].concat();
    let push = |d: &openh264::decoder::DecodedYUV<'_>, frames: &mut Vec<Vec<u8>>| {
        let (w, h) = openh264::formats::YUVSource::dimensions(d);
        let mut rgb = vec![0u8; w * h * 3];
        d.write_rgb8(&mut rgb);
        frames.push(rgb);
    };
    for k in 1..=count {
        let Some(s) = mp4
            .read_sample(id, k)
            .map_err(|e| codec(format!("sample {k}: {e}")))?
        else {
            continue;
        };
        if k == 1 {
            fps = timescale as f64 / s.duration.max(1) as f64;
            for p in [&sps, &pps] {
                decoder
                    .decode(&annex(p))
                    .map_err(|e| codec(format!("the parameter sets: {e}")))?;
            }
        }
        let mut packet = Vec::new();
        let mut rest = &s.bytes[..];
        while rest.len() >= 4 {
            let n = u32::from_be_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
            if rest.len() < 4 + n {
                return Err(codec(format!("sample {k}: a NAL unit runs past its end")));
            }
            packet.extend(annex(&rest[4..4 + n]));
            rest = &rest[4 + n..];
        }
        if let Some(d) = decoder
            .decode(&packet)
            .map_err(|e| codec(format!("decoding sample {k}: {e}")))?
        {
            push(&d, &mut frames);
        }
    }
    for d in decoder
        .flush_remaining()
        .map_err(|e| codec(format!("the decoder's last frames: {e}")))?
    {
        push(&d, &mut frames);
    }
    Ok(DecodedVideo {
        width,
        height,
        fps,
        frames,
    })
}
