//! The `.txt` layout: one record per line (images: two), `#` comments, `-1` for "no 3D point".

use std::path::Path;
use std::str::FromStr;

use super::{ColmapCamera, ColmapError, ColmapImage, ColmapPoint, model_by_name, valid_quaternion};

/// The file's lines, numbered from 1.
fn lines(path: &Path) -> Result<Vec<(usize, String)>, ColmapError> {
    let data = std::fs::read(path).map_err(|e| ColmapError::Io {
        path: path.to_path_buf(),
        action: "read",
        message: e.to_string(),
    })?;
    let text = String::from_utf8(data).map_err(|e| {
        let bad = e.utf8_error().valid_up_to();
        let line = e.as_bytes()[..bad].iter().filter(|b| **b == b'\n').count() + 1;
        ColmapError::Text {
            path: path.to_path_buf(),
            line,
            message: "line is not UTF-8 text".into(),
        }
    })?;
    Ok(text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r').to_string()))
        .collect())
}

/// Whether a line holds no record.
fn skip(line: &str) -> bool {
    let t = line.trim_start();
    t.is_empty() || t.starts_with('#')
}

/// Parses one whitespace-separated field, naming it in the error.
fn field<T: FromStr>(
    path: &Path,
    line: usize,
    token: Option<&str>,
    name: &str,
) -> Result<T, ColmapError> {
    let err = |message: String| ColmapError::Text {
        path: path.to_path_buf(),
        line,
        message,
    };
    let t = token.ok_or_else(|| err(format!("missing field `{name}`")))?;
    t.parse()
        .map_err(|_| err(format!("field `{name}`: cannot parse `{t}`")))
}

/// `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
pub(super) fn cameras(path: &Path) -> Result<Vec<ColmapCamera>, ColmapError> {
    let mut out = Vec::new();
    for (n, line) in lines(path)? {
        if skip(&line) {
            continue;
        }
        let mut t = line.split_ascii_whitespace();
        let id = field(path, n, t.next(), "CAMERA_ID")?;
        let model_name: String = field(path, n, t.next(), "MODEL")?;
        let Some((model, count)) = model_by_name(&model_name) else {
            return Err(ColmapError::Text {
                path: path.to_path_buf(),
                line: n,
                message: format!("unknown camera model `{model_name}`"),
            });
        };
        let width = field(path, n, t.next(), "WIDTH")?;
        let height = field(path, n, t.next(), "HEIGHT")?;
        let params = t
            .map(|v| field(path, n, Some(v), "PARAMS"))
            .collect::<Result<Vec<f64>, _>>()?;
        if params.len() != count {
            return Err(ColmapError::Text {
                path: path.to_path_buf(),
                line: n,
                message: format!(
                    "camera model {model} takes {count} parameters, the line has {}",
                    params.len()
                ),
            });
        }
        out.push(ColmapCamera {
            id,
            model: model.to_string(),
            width,
            height,
            params,
        });
    }
    Ok(out)
}

/// Pairs of lines: `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, then `(X Y POINT3D_ID)*`
/// (possibly empty).
pub(super) fn images(path: &Path) -> Result<Vec<ColmapImage>, ColmapError> {
    let all = lines(path)?;
    let mut it = all.iter();
    let mut out = Vec::new();
    while let Some((n, line)) = it.next() {
        let n = *n;
        if skip(line) {
            continue;
        }
        let err = |line: usize, message: String| ColmapError::Text {
            path: path.to_path_buf(),
            line,
            message,
        };
        let tokens: Vec<&str> = line.split_ascii_whitespace().collect();
        if tokens.len() != 10 {
            return Err(err(
                n,
                format!(
                    "expected 10 fields `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, found {}",
                    tokens.len()
                ),
            ));
        }
        let f = |i: usize, name: &str| field::<f64>(path, n, Some(tokens[i]), name);
        let id = field(path, n, Some(tokens[0]), "IMAGE_ID")?;
        let qvec_wxyz = [f(1, "QW")?, f(2, "QX")?, f(3, "QY")?, f(4, "QZ")?];
        if !valid_quaternion(&qvec_wxyz) {
            return Err(err(
                n,
                format!("quaternion {qvec_wxyz:?} is zero or not finite"),
            ));
        }
        let tvec = [f(5, "TX")?, f(6, "TY")?, f(7, "TZ")?];
        let camera_id = field(path, n, Some(tokens[8]), "CAMERA_ID")?;
        let name = tokens[9].to_string();
        // The keypoint line; absent at the end of the file means no keypoints.
        let mut points2d = Vec::new();
        if let Some((m, kp)) = it.next() {
            let t: Vec<&str> = kp.split_ascii_whitespace().collect();
            if !t.len().is_multiple_of(3) {
                return Err(err(
                    *m,
                    format!(
                        "keypoints of image {id}: {} values, not a multiple of 3 (X Y POINT3D_ID)",
                        t.len()
                    ),
                ));
            }
            points2d.reserve(t.len() / 3);
            for c in t.chunks_exact(3) {
                let x = field(path, *m, Some(c[0]), "X")?;
                let y = field(path, *m, Some(c[1]), "Y")?;
                let p = if c[2] == "-1" {
                    None
                } else {
                    Some(field(path, *m, Some(c[2]), "POINT3D_ID")?)
                };
                points2d.push(([x, y], p));
            }
        }
        out.push(ColmapImage {
            id,
            name,
            camera_id,
            qvec_wxyz,
            tvec,
            points2d,
        });
    }
    Ok(out)
}

/// `POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)*`.
pub(super) fn points(path: &Path) -> Result<Vec<ColmapPoint>, ColmapError> {
    let mut out = Vec::new();
    for (n, line) in lines(path)? {
        if skip(&line) {
            continue;
        }
        let t: Vec<&str> = line.split_ascii_whitespace().collect();
        if t.len() < 8 || !(t.len() - 8).is_multiple_of(2) {
            return Err(ColmapError::Text {
                path: path.to_path_buf(),
                line: n,
                message: format!(
                    "{} fields; expected `POINT3D_ID X Y Z R G B ERROR` and (IMAGE_ID POINT2D_IDX) pairs",
                    t.len()
                ),
            });
        }
        let f = |i: usize, name: &str| field::<f64>(path, n, Some(t[i]), name);
        let u = |i: usize, name: &str| field::<u8>(path, n, Some(t[i]), name);
        let track = t[8..]
            .chunks_exact(2)
            .map(|p| {
                Ok((
                    field(path, n, Some(p[0]), "IMAGE_ID")?,
                    field(path, n, Some(p[1]), "POINT2D_IDX")?,
                ))
            })
            .collect::<Result<Vec<_>, ColmapError>>()?;
        out.push(ColmapPoint {
            id: field(path, n, Some(t[0]), "POINT3D_ID")?,
            xyz: [f(1, "X")?, f(2, "Y")?, f(3, "Z")?],
            rgb: [u(4, "R")?, u(5, "G")?, u(6, "B")?],
            error: f(7, "ERROR")?,
            track,
        });
    }
    Ok(out)
}
