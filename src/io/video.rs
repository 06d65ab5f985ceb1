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
