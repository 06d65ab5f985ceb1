//! Points with named per-point scalars (e.g. a ground-truth material: `x y z E nu`), the
//! format of `gt/material_particles.ply`.

use std::io::Write;
use std::path::Path;

use super::PlyError;
use super::body::Source;
use super::write::write_atomic;

/// Positions (metres) and one column per scalar, in the order asked.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PointScalars {
    /// Positions, metres.
    pub positions: Vec<[f32; 3]>,
    /// One column per name asked, each as long as `positions`.
    pub columns: Vec<Vec<f64>>,
}

/// Reads the vertices' `x y z` and the scalar properties `names` (any numeric type); a missing
/// property, a list property or a non-finite value is an error naming the file, the property
/// and the record.
pub fn read_point_scalars(path: &Path, names: &[&str]) -> Result<PointScalars, PlyError> {
    let mut src = Source::open(path)?;
    let (target, el) = src
        .header()
        .element("vertex")
        .ok_or_else(|| PlyError::MissingElement {
            path: path.to_path_buf(),
            element: "vertex".into(),
        })?;
    let el = el.clone();
    let mut index = Vec::with_capacity(3 + names.len());
    for name in ["x", "y", "z"].iter().chain(names) {
        match el.scalar(name) {
            None => {
                return Err(PlyError::MissingProperty {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    property: (*name).to_string(),
                });
            }
            Some((i, Ok(_))) => index.push(i),
            Some((i, Err(_))) => {
                return Err(PlyError::PropertyType {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    property: el.properties[i].name.clone(),
                    found: el.properties[i].kind.describe(),
                    expected: "a scalar",
                });
            }
        }
    }
    let cap = src.capacity_hint(&el);
    let mut out = PointScalars {
        positions: Vec::with_capacity(cap),
        columns: vec![Vec::with_capacity(cap); names.len()],
    };
    src.read_element(target, &mut |record, v| {
        for &i in &index {
            if !v[i].is_finite() {
                return Err(PlyError::Value {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    record,
                    property: el.properties[i].name.clone(),
                    message: format!("{} is not finite", v[i]),
                });
            }
        }
        out.positions
            .push([v[index[0]] as f32, v[index[1]] as f32, v[index[2]] as f32]);
        for (c, &i) in out.columns.iter_mut().zip(&index[3..]) {
            c.push(v[i]);
        }
        Ok(())
    })?;
    Ok(out)
}

/// Writes `float x y z` and one `double` property per named column (binary little endian,
/// atomically). Columns must be as long as `positions` and finite.
pub fn write_point_scalars(
    path: &Path,
    positions: &[[f32; 3]],
    columns: &[(&str, &[f64])],
) -> Result<(), PlyError> {
    let invalid = |message: String| PlyError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    for (name, c) in columns {
        if c.len() != positions.len() {
            return Err(invalid(format!(
                "{} values of `{name}` for {} positions",
                c.len(),
                positions.len()
            )));
        }
        if let Some(i) = c.iter().position(|v| !v.is_finite()) {
            return Err(invalid(format!("`{name}` of point {i} is {}", c[i])));
        }
        if name.is_empty() || name.contains(char::is_whitespace) {
            return Err(invalid(format!("property name {name:?}")));
        }
    }
    if let Some(i) = positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(invalid(format!("position {i} is {:?}", positions[i])));
    }
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n",
        positions.len()
    );
    for (name, _) in columns {
        header += &format!("property double {name}\n");
    }
    header += "end_header\n";
    let mut body = Vec::with_capacity(header.len() + (12 + 8 * columns.len()) * positions.len());
    body.extend_from_slice(header.as_bytes());
    for (i, p) in positions.iter().enumerate() {
        for v in p {
            body.extend_from_slice(&v.to_le_bytes());
        }
        for (_, c) in columns {
            body.extend_from_slice(&c[i].to_le_bytes());
        }
    }
    write_atomic(path, |w| w.write_all(&body))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalars_round_trip_and_bad_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.ply");
        let x = [[0.0f32, 1.0, 2.0], [3.0, 4.0, 5.0]];
        let e = [2e4, 6e5];
        let nu = [0.3, 0.25];
        write_point_scalars(&path, &x, &[("E", &e), ("nu", &nu)]).unwrap();
        let r = read_point_scalars(&path, &["nu", "E"]).unwrap();
        assert_eq!(r.positions, x);
        assert_eq!(r.columns, vec![nu.to_vec(), e.to_vec()]);
        let err = read_point_scalars(&path, &["yield"])
            .unwrap_err()
            .to_string();
        assert!(err.contains("m.ply") && err.contains("yield"), "{err}");
        let err = write_point_scalars(&path, &x, &[("E", &e[..1])])
            .unwrap_err()
            .to_string();
        assert!(err.contains("1 values of `E` for 2"), "{err}");
        let err = write_point_scalars(&path, &x, &[("E", &[1.0, f64::NAN])])
            .unwrap_err()
            .to_string();
        assert!(err.contains("`E` of point 1 is NaN"), "{err}");
    }
}
