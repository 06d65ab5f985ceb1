//! 3DGS `point_cloud.ply` ↔ [`Gaussians`].
//!
//! The layout of graphdeco-inria/gaussian-splatting: element `vertex` with `x y z nx ny nz
//! f_dc_0..2 f_rest_0..f_rest_{3·((d+1)²−1)−1} opacity scale_0..2 rot_0..3`. Stored values are
//! the raw parameters (opacity logit, log scale, unnormalised (w, x, y, z) quaternion).
//! `f_rest` is channel-major: `f_rest_i` is coefficient k = i mod (K−1) + 1 of channel
//! c = i div (K−1), K = (d+1)²; ours is `[k][channel]`.

use std::io::Write;
use std::path::Path;

use super::PlyError;
use super::body::Source;
use super::header::Element;
use super::write::write_atomic;
use crate::scene::gaussians::{Gaussians, sh_coeffs};

/// Column indices of the 3DGS properties in the `vertex` element.
struct Columns {
    position: [usize; 3],
    dc: [usize; 3],
    rest: Vec<usize>,
    opacity: usize,
    scale: [usize; 3],
    rot: [usize; 4],
}

impl Columns {
    /// Every index used.
    fn all(&self) -> Vec<usize> {
        let mut v = Vec::with_capacity(14 + self.rest.len());
        v.extend(self.position);
        v.extend(self.dc);
        v.extend(&self.rest);
        v.push(self.opacity);
        v.extend(self.scale);
        v.extend(self.rot);
        v
    }

    /// Finds every property (float or double), and the SH degree from the `f_rest_*` count.
    fn find(el: &Element, path: &Path) -> Result<(Self, u8), PlyError> {
        let col = |name: &str| -> Result<usize, PlyError> {
            match el.scalar(name) {
                None => Err(PlyError::MissingProperty {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    property: name.to_string(),
                }),
                Some((i, Ok(s))) if s.is_float() => Ok(i),
                Some((i, _)) => Err(PlyError::PropertyType {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    property: name.to_string(),
                    found: el.properties[i].kind.describe(),
                    expected: "`float` or `double`",
                }),
            }
        };
        let cols = |names: &[&str]| names.iter().map(|n| col(n)).collect::<Result<Vec<_>, _>>();
        let n_rest = el
            .properties
            .iter()
            .filter(|p| p.name.starts_with("f_rest_"))
            .count();
        let degree = match n_rest {
            0 => 0,
            9 => 1,
            24 => 2,
            45 => 3,
            n => {
                return Err(PlyError::ShRest {
                    path: path.to_path_buf(),
                    message: format!(
                        "{n} `f_rest_*` properties; 3DGS files have 0, 9, 24 or 45 (SH degree 0..=3)"
                    ),
                });
            }
        };
        let rest = (0..n_rest)
            .map(|i| {
                col(&format!("f_rest_{i}")).map_err(|e| match e {
                    PlyError::MissingProperty { .. } => PlyError::ShRest {
                        path: path.to_path_buf(),
                        message: format!(
                            "{n_rest} `f_rest_*` properties but no `f_rest_{i}` (expected f_rest_0..f_rest_{})",
                            n_rest - 1
                        ),
                    },
                    other => other,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let p = cols(&["x", "y", "z"])?;
        let dc = cols(&["f_dc_0", "f_dc_1", "f_dc_2"])?;
        let scale = cols(&["scale_0", "scale_1", "scale_2"])?;
        let rot = cols(&["rot_0", "rot_1", "rot_2", "rot_3"])?;
        Ok((
            Self {
                position: [p[0], p[1], p[2]],
                dc: [dc[0], dc[1], dc[2]],
                rest,
                opacity: col("opacity")?,
                scale: [scale[0], scale[1], scale[2]],
                rot: [rot[0], rot[1], rot[2], rot[3]],
            },
            degree,
        ))
    }
}

/// Reads a 3DGS PLY: ids 0..n, every Gaussian simulated. Non-finite values are an error
/// naming the record and property.
pub fn read_gaussians(path: &Path) -> Result<Gaussians, PlyError> {
    let mut src = Source::open(path)?;
    let (target, el) = src
        .header()
        .element("vertex")
        .ok_or_else(|| PlyError::MissingElement {
            path: path.to_path_buf(),
            element: "vertex".into(),
        })?;
    let el = el.clone();
    let (cols, degree) = Columns::find(&el, path)?;
    let k_count = sh_coeffs(degree);
    let cap = src.capacity_hint(&el);
    let mut g = Gaussians {
        sh_degree: degree,
        id: Vec::with_capacity(cap),
        position: Vec::with_capacity(cap),
        log_scale: Vec::with_capacity(cap),
        rotation: Vec::with_capacity(cap),
        opacity_logit: Vec::with_capacity(cap),
        sh: Vec::with_capacity(cap.saturating_mul(3 * k_count)),
        simulated: Vec::with_capacity(cap),
    };
    let mut sh = vec![0f32; 3 * k_count];
    let used = cols.all();
    src.read_element(target, &mut |record, v| {
        for &i in &used {
            let value = v[i];
            // Also catches doubles beyond the f32 range.
            if !(value as f32).is_finite() {
                return Err(PlyError::Value {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    record,
                    property: el.properties[i].name.clone(),
                    message: format!("value {value} is not a finite f32"),
                });
            }
        }
        let f = |i: usize| v[i] as f32;
        for c in 0..3 {
            sh[c] = f(cols.dc[c]);
            for k in 1..k_count {
                sh[3 * k + c] = f(cols.rest[c * (k_count - 1) + (k - 1)]);
            }
        }
        let id = u32::try_from(record).map_err(|_| PlyError::Value {
            path: path.to_path_buf(),
            element: el.name.clone(),
            record,
            property: "x".into(),
            message: "more Gaussians than u32 ids".into(),
        })?;
        g.id.push(id);
        g.position.push(cols.position.map(f));
        g.log_scale.push(cols.scale.map(f));
        g.rotation.push(cols.rot.map(f));
        g.opacity_logit.push(f(cols.opacity));
        g.sh.extend_from_slice(&sh);
        g.simulated.push(true);
        Ok(())
    })?;
    Ok(g)
}

/// Writes `g` as a 3DGS PLY (binary little endian, normals 0), atomically. The file has no
/// place for `id` and `simulated`: reading it back gives ids 0..n, all simulated.
pub fn write_gaussians(path: &Path, g: &Gaussians) -> Result<(), PlyError> {
    check(path, g)?;
    let n = g.len();
    let k_count = sh_coeffs(g.sh_degree);
    let n_rest = 3 * (k_count - 1);
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    for name in [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ] {
        header += &format!("property float {name}\n");
    }
    for i in 0..n_rest {
        header += &format!("property float f_rest_{i}\n");
    }
    for name in [
        "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        header += &format!("property float {name}\n");
    }
    header += "end_header\n";
    write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut record = Vec::with_capacity(4 * (17 + n_rest));
        for i in 0..n {
            record.clear();
            let sh = &g.sh[i * 3 * k_count..(i + 1) * 3 * k_count];
            let mut put = |v: f32| record.extend_from_slice(&v.to_le_bytes());
            g.position[i].into_iter().for_each(&mut put);
            [0.0; 3].into_iter().for_each(&mut put);
            sh[..3].iter().copied().for_each(&mut put);
            for c in 0..3 {
                for k in 1..k_count {
                    put(sh[3 * k + c]);
                }
            }
            put(g.opacity_logit[i]);
            g.log_scale[i].into_iter().for_each(&mut put);
            g.rotation[i].into_iter().for_each(&mut put);
            w.write_all(&record)?;
        }
        Ok(())
    })
}

/// Field lengths agree and every value is finite (what [`read_gaussians`] accepts).
fn check(path: &Path, g: &Gaussians) -> Result<(), PlyError> {
    let invalid = |message: String| PlyError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    if g.sh_degree > 3 {
        return Err(invalid(format!(
            "SH degree {} is not in 0..=3",
            g.sh_degree
        )));
    }
    let n = g.len();
    let per = 3 * sh_coeffs(g.sh_degree);
    let lens = [
        ("position", g.position.len(), n),
        ("log_scale", g.log_scale.len(), n),
        ("rotation", g.rotation.len(), n),
        ("opacity_logit", g.opacity_logit.len(), n),
        ("simulated", g.simulated.len(), n),
        ("sh", g.sh.len(), n * per),
    ];
    for (field, len, want) in lens {
        if len != want {
            return Err(invalid(format!(
                "field `{field}` has {len} values, {n} Gaussians of SH degree {} need {want}",
                g.sh_degree
            )));
        }
    }
    for i in 0..n {
        let fields: [(&str, &[f32]); 5] = [
            ("position", &g.position[i]),
            ("log_scale", &g.log_scale[i]),
            ("rotation", &g.rotation[i]),
            ("opacity_logit", std::slice::from_ref(&g.opacity_logit[i])),
            ("sh", &g.sh[i * per..(i + 1) * per]),
        ];
        for (field, values) in fields {
            if let Some(v) = values.iter().find(|v| !v.is_finite()) {
                return Err(invalid(format!("Gaussian {i} field `{field}` holds {v}")));
            }
        }
    }
    Ok(())
}
