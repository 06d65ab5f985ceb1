//! Point clouds: any PLY with `x y z` (float or double) and optionally `red green blue`
//! (uchar, scaled by 1/255, or float/double in [0, 1]).

use std::io::Write;
use std::path::Path;

use super::body::Source;
use super::header::Element;
use super::write::write_atomic;
use super::{PlyError, PointCloud};

/// Where a colour channel is and how to scale it.
#[derive(Debug, Clone, Copy)]
struct Channel {
    index: usize,
    /// 1/255 for uchar, 1 for float/double.
    scale: f64,
    /// Float/double: must lie in [0, 1].
    float: bool,
}

/// Reads positions (metres) and colours. Extra properties and elements are ignored; a
/// non-finite coordinate or a float colour outside [0, 1] is an error naming the record.
pub fn read_points(path: &Path) -> Result<PointCloud, PlyError> {
    let mut src = Source::open(path)?;
    let (target, el) = src
        .header()
        .element("vertex")
        .ok_or_else(|| PlyError::MissingElement {
            path: path.to_path_buf(),
            element: "vertex".into(),
        })?;
    let el = el.clone();
    let property_type = |i: usize, expected| PlyError::PropertyType {
        path: path.to_path_buf(),
        element: el.name.clone(),
        property: el.properties[i].name.clone(),
        found: el.properties[i].kind.describe(),
        expected,
    };
    let mut xyz = [0usize; 3];
    for (slot, name) in xyz.iter_mut().zip(["x", "y", "z"]) {
        *slot = match el.scalar(name) {
            None => return Err(missing(path, &el, name)),
            Some((i, Ok(s))) if s.is_float() => i,
            Some((i, _)) => return Err(property_type(i, "`float` or `double`")),
        };
    }
    let rgb = ["red", "green", "blue"].map(|n| el.scalar(n));
    let colors = if rgb.iter().all(Option::is_none) {
        None
    } else {
        let mut ch = [Channel {
            index: 0,
            scale: 1.0,
            float: true,
        }; 3];
        for (c, (found, name)) in ch
            .iter_mut()
            .zip(rgb.into_iter().zip(["red", "green", "blue"]))
        {
            *c = match found {
                None => return Err(missing(path, &el, name)),
                Some((i, Ok(super::header::Scalar::U8))) => Channel {
                    index: i,
                    scale: 1.0 / 255.0,
                    float: false,
                },
                Some((i, Ok(s))) if s.is_float() => Channel {
                    index: i,
                    scale: 1.0,
                    float: true,
                },
                Some((i, _)) => return Err(property_type(i, "`uchar`, `float` or `double`")),
            };
        }
        Some(ch)
    };
    let cap = src.capacity_hint(&el);
    let mut positions = Vec::with_capacity(cap);
    let mut rgb_out = Vec::with_capacity(if colors.is_some() { cap } else { 0 });
    src.read_element(target, &mut |record, v| {
        let value_err = |i: usize, message: String| PlyError::Value {
            path: path.to_path_buf(),
            element: el.name.clone(),
            record,
            property: el.properties[i].name.clone(),
            message,
        };
        for &i in &xyz {
            if !(v[i] as f32).is_finite() {
                return Err(value_err(
                    i,
                    format!("coordinate {} is not a finite f32", v[i]),
                ));
            }
        }
        positions.push(xyz.map(|i| v[i] as f32));
        if let Some(ch) = colors {
            for c in ch {
                let x = v[c.index];
                if c.float && !(0.0..=1.0).contains(&x) {
                    return Err(value_err(c.index, format!("colour {x} is outside [0, 1]")));
                }
            }
            rgb_out.push(ch.map(|c| (v[c.index] * c.scale) as f32));
        }
        Ok(())
    })?;
    Ok(PointCloud {
        positions,
        colors: colors.map(|_| rgb_out),
    })
}

fn missing(path: &Path, el: &Element, property: &str) -> PlyError {
    PlyError::MissingProperty {
        path: path.to_path_buf(),
        element: el.name.clone(),
        property: property.to_string(),
    }
}

/// Writes `float x y z` (metres) and, with colours, `uchar red green blue` (round(255·c), c
/// clamped to [0, 1]); binary little endian, atomically.
pub fn write_points(
    path: &Path,
    positions: &[[f32; 3]],
    colors: Option<&[[f32; 3]]>,
) -> Result<(), PlyError> {
    let invalid = |message: String| PlyError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    if let Some(c) = colors
        && c.len() != positions.len()
    {
        return Err(invalid(format!(
            "{} colours for {} positions",
            c.len(),
            positions.len()
        )));
    }
    if let Some(i) = positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(invalid(format!("position {i} is {:?}", positions[i])));
    }
    if let Some(c) = colors
        && let Some(i) = c.iter().position(|p| p.iter().any(|v| v.is_nan()))
    {
        return Err(invalid(format!("colour {i} is {:?}", c[i])));
    }
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n",
        positions.len()
    );
    if colors.is_some() {
        header += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    }
    header += "end_header\n";
    // The vertices serialised in memory first: one write instead of one per value.
    let stride = 12 + if colors.is_some() { 3 } else { 0 };
    let mut body = Vec::with_capacity(header.len() + stride * positions.len());
    body.extend_from_slice(header.as_bytes());
    for (i, p) in positions.iter().enumerate() {
        for v in p {
            body.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(c) = colors {
            body.extend_from_slice(&c[i].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8));
        }
    }
    write_atomic(path, |w| w.write_all(&body))
}
