//! Frame sequences as videos: an animated GIF (the `image` crate's encoder) and, when
//! `ffmpeg` is on `PATH`, an H.264 MP4 of numbered PNGs.

use std::path::Path;
use std::process::Command;

use super::image::{ImageError, Rgb8};

/// An animated GIF of `frames` (all the same size), `ms` per frame, looping.
pub fn write_gif(path: &Path, frames: &[Rgb8], ms: u32) -> Result<(), ImageError> {
    use ::image::codecs::gif::{GifEncoder, Repeat};
    use ::image::{Delay, Frame, RgbaImage};
    let io = |e: &dyn std::fmt::Display| ImageError::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let file = std::fs::File::create(path).map_err(|e| io(&e))?;
    let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 10);
    enc.set_repeat(Repeat::Infinite).map_err(|e| io(&e))?;
    for f in frames {
        let rgba: Vec<u8> = f
            .data
            .chunks_exact(3)
            .flat_map(|c| [c[0], c[1], c[2], 255])
            .collect();
        let img = RgbaImage::from_raw(f.width, f.height, rgba)
            .ok_or_else(|| io(&"frames of different sizes"))?;
        enc.encode_frame(Frame::from_parts(
            img,
            0,
            0,
            Delay::from_numer_denom_ms(ms, 1),
        ))
        .map_err(|e| io(&e))?;
    }
    Ok(())
}

/// What became of an MP4.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Mp4 {
    /// Written.
    Written,
    /// `ffmpeg` is not on `PATH`: nothing written.
    NoFfmpeg,
    /// `ffmpeg` ran and failed (its message).
    Failed(String),
}

/// Encodes the PNGs `pattern` (an `ffmpeg` image pattern, e.g. `dir/%04d.png`, numbered from
/// 0) into `out` at `fps` frames per second: H.264, yuv420p (odd sizes padded by a pixel),
/// single-threaded and without encoder or time stamps in the file, so the same frames give
/// the same bytes.
pub fn write_mp4(pattern: &Path, out: &Path, fps: f64) -> Mp4 {
    let run = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-nostdin", "-y"])
        .args(["-framerate", &format!("{fps}")])
        .arg("-i")
        .arg(pattern)
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-threads",
            "1",
            "-map_metadata",
            "-1",
            "-fflags",
            "+bitexact",
            "-flags:v",
            "+bitexact",
        ])
        .arg(out)
        .output();
    match run {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Mp4::NoFfmpeg,
        Err(e) => Mp4::Failed(format!("cannot run ffmpeg: {e}")),
        Ok(o) if o.status.success() => Mp4::Written,
        Ok(o) => Mp4::Failed(format!(
            "ffmpeg failed ({}): {}",
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        )),
    }
}

/// A video file as `ffprobe` describes its first video stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VideoInfo {
    /// Frame size (pixels).
    pub width: u32,
    pub height: u32,
    /// Frames in the stream (packets counted, nothing decoded).
    pub frames: usize,
    /// Frames per second (the stream's average frame rate), if it states one.
    pub fps: Option<f64>,
}

/// Why a video cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    /// `ffmpeg`/`ffprobe` is not on `PATH`.
    #[error(
        "{path}: reading videos needs `{tool}` (FFmpeg) on PATH: install it (Debian: `apt-get \
         install ffmpeg`) or extract the frames into a folder of PNGs"
    )]
    NoFfmpeg {
        /// The video.
        path: std::path::PathBuf,
        /// `ffprobe` or `ffmpeg`.
        tool: &'static str,
    },
    /// The tool ran and failed, or its output makes no sense.
    #[error("{path}: {message}")]
    Failed {
        /// The video.
        path: std::path::PathBuf,
        /// What went wrong (the tool's message).
        message: String,
    },
}

fn run_tool(tool: &'static str, path: &Path, args: &[&str]) -> Result<Vec<u8>, VideoError> {
    let out = Command::new(tool)
        .args(["-hide_banner", "-loglevel", "error"])
        .args(args)
        .output()
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => VideoError::NoFfmpeg {
                path: path.to_path_buf(),
                tool,
            },
            _ => VideoError::Failed {
                path: path.to_path_buf(),
                message: format!("cannot run {tool}: {e}"),
            },
        })?;
    if !out.status.success() {
        return Err(VideoError::Failed {
            path: path.to_path_buf(),
            message: format!(
                "{tool} failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(out.stdout)
}

/// The size, frame count and rate of `path`'s first video stream (`ffprobe`).
pub fn probe(path: &Path) -> Result<VideoInfo, VideoError> {
    let p = path.to_string_lossy();
    let out = run_tool(
        "ffprobe",
        path,
        &[
            "-select_streams",
            "v:0",
            "-count_packets",
            "-show_entries",
            "stream=width,height,avg_frame_rate,nb_read_packets",
            "-of",
            "default=noprint_wrappers=1",
            &p,
        ],
    )?;
    let text = String::from_utf8_lossy(&out);
    let field = |k: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("{k}=")))
            .map(str::trim)
    };
    let bad = |message: String| VideoError::Failed {
        path: path.to_path_buf(),
        message,
    };
    let int = |k: &str| -> Result<u64, VideoError> {
        field(k).and_then(|v| v.parse().ok()).ok_or_else(|| {
            bad(format!(
                "no video stream with a `{k}` (ffprobe said: {text:?})"
            ))
        })
    };
    let (width, height, frames) = (int("width")?, int("height")?, int("nb_read_packets")?);
    if width == 0 || height == 0 || frames == 0 {
        return Err(bad(format!(
            "{width}×{height} pixels, {frames} frames: an empty video"
        )));
    }
    let fps = field("avg_frame_rate").and_then(|r| {
        let (n, d) = r.split_once('/')?;
        let v = n.parse::<f64>().ok()? / d.parse::<f64>().ok()?;
        (v.is_finite() && v > 0.0).then_some(v)
    });
    Ok(VideoInfo {
        width: width as u32,
        height: height as u32,
        frames: frames as usize,
        fps,
    })
}

/// Every frame of `path`'s first video stream as 8-bit RGB (`ffmpeg`, one frame per packet:
/// no frame dropped or repeated).
pub fn decode(path: &Path) -> Result<Vec<Rgb8>, VideoError> {
    let info = probe(path)?;
    let p = path.to_string_lossy();
    let raw = run_tool(
        "ffmpeg",
        path,
        &[
            "-nostdin",
            "-i",
            &p,
            "-map",
            "0:v:0",
            "-fps_mode",
            "passthrough",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-",
        ],
    )?;
    let size = info.width as usize * info.height as usize * 3;
    if raw.len() % size != 0 || raw.is_empty() {
        return Err(VideoError::Failed {
            path: path.to_path_buf(),
            message: format!(
                "ffmpeg gave {} bytes, not a whole number of {}×{} RGB frames",
                raw.len(),
                info.width,
                info.height
            ),
        });
    }
    Ok(raw
        .chunks_exact(size)
        .map(|c| Rgb8 {
            width: info.width,
            height: info.height,
            data: c.to_vec(),
        })
        .collect())
}

/// Videos decoded in this process, by path: `ingest` reads a video's frames one at a time
/// (all cameras of frame 0, then frame 1, ...), and decodes each video once.
static DECODED: std::sync::Mutex<Vec<(std::path::PathBuf, std::sync::Arc<Vec<Rgb8>>)>> =
    std::sync::Mutex::new(Vec::new());

/// Frame `index` of the video `path`, decoding the video on first use (kept until
/// [`forget_decoded`]).
pub fn frame(path: &Path, index: usize) -> Result<Rgb8, VideoError> {
    let cached = DECODED
        .lock()
        .map_err(|_| VideoError::Failed {
            path: path.to_path_buf(),
            message: "the decoded-video cache is poisoned".into(),
        })?
        .iter()
        .find(|(p, _)| p == path)
        .map(|(_, f)| f.clone());
    let frames = match cached {
        Some(f) => f,
        None => {
            let f = std::sync::Arc::new(decode(path)?);
            if let Ok(mut d) = DECODED.lock() {
                d.push((path.to_path_buf(), f.clone()));
            }
            f
        }
    };
    frames
        .get(index)
        .cloned()
        .ok_or_else(|| VideoError::Failed {
            path: path.to_path_buf(),
            message: format!("has {} frames, no frame {index}", frames.len()),
        })
}

/// Drops the decoded videos [`frame`] kept.
pub fn forget_decoded() {
    if let Ok(mut d) = DECODED.lock() {
        d.clear();
    }
}
