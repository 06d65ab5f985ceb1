//! The `.bin` layout (little endian, no padding): a u64 record count, then the records.

use std::path::Path;

use super::{ColmapCamera, ColmapError, ColmapImage, ColmapPoint, model_by_id, valid_quaternion};

/// `point3D_id` of a keypoint without a 3D point.
const NO_POINT: u64 = u64::MAX;

/// A position in a file's bytes and the record being read (for error messages).
struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
    kind: &'static str,
    record: u64,
    count: u64,
}

impl<'a> Cursor<'a> {
    fn record_name(&self) -> String {
        if self.count == 0 {
            "the record count".to_string()
        } else {
            format!("{} record {} of {}", self.kind, self.record, self.count)
        }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], ColmapError> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.data.len());
        let Some(end) = end else {
            return Err(ColmapError::Truncated {
                path: self.path.to_path_buf(),
                record: self.record_name(),
                needed: n as u64,
                offset: self.pos as u64,
                file_len: self.data.len() as u64,
            });
        };
        let b = &self.data[self.pos..end];
        self.pos = end;
        Ok(b)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], ColmapError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    fn u32(&mut self) -> Result<u32, ColmapError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn i32(&mut self) -> Result<i32, ColmapError> {
        Ok(i32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> Result<u64, ColmapError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    fn f64(&mut self) -> Result<f64, ColmapError> {
        Ok(f64::from_le_bytes(self.array()?))
    }

    fn f64s<const N: usize>(&mut self) -> Result<[f64; N], ColmapError> {
        let mut a = [0.0; N];
        for v in &mut a {
            *v = self.f64()?;
        }
        Ok(a)
    }

    fn error(&self, offset: usize, message: String) -> ColmapError {
        ColmapError::Binary {
            path: self.path.to_path_buf(),
            record: self.record_name(),
            offset: offset as u64,
            message,
        }
    }

    /// A u64 count of items of at least `min_bytes` each, checked against the bytes left.
    fn count(&mut self, min_bytes: u64, what: &str) -> Result<usize, ColmapError> {
        let at = self.pos;
        let n = self.u64()?;
        let left = (self.data.len() - self.pos) as u64;
        if n.checked_mul(min_bytes).is_none_or(|b| b > left) {
            return Err(self.error(
                at,
                format!(
                    "{n} {what} of at least {min_bytes} bytes each, but only {left} bytes follow"
                ),
            ));
        }
        Ok(n as usize)
    }

    /// After the last record: nothing may be left.
    fn finish(&self) -> Result<(), ColmapError> {
        let left = self.data.len() - self.pos;
        if left > 0 {
            return Err(ColmapError::Binary {
                path: self.path.to_path_buf(),
                record: format!("after the last of {} records", self.count),
                offset: self.pos as u64,
                message: format!("{left} unexpected trailing bytes"),
            });
        }
        Ok(())
    }
}

/// Reads `path` whole and calls `body` with a cursor after the record count.
fn read<T>(
    path: &Path,
    kind: &'static str,
    min_record: u64,
    mut record: impl FnMut(&mut Cursor<'_>) -> Result<T, ColmapError>,
) -> Result<Vec<T>, ColmapError> {
    let data = std::fs::read(path).map_err(|e| ColmapError::Io {
        path: path.to_path_buf(),
        action: "read",
        message: e.to_string(),
    })?;
    let mut c = Cursor {
        data: &data,
        pos: 0,
        path,
        kind,
        record: 0,
        count: 0,
    };
    let n = c.count(min_record, &format!("{kind} records"))?;
    c.count = n as u64;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        c.record = i as u64;
        out.push(record(&mut c)?);
    }
    c.finish()?;
    Ok(out)
}

/// `cameras.bin`: u32 id, i32 model id, u64 width, u64 height, f64 params[n(model)].
pub(super) fn cameras(path: &Path) -> Result<Vec<ColmapCamera>, ColmapError> {
    read(path, "camera", 24, |c| {
        let id = c.u32()?;
        let at = c.pos;
        let model_id = c.i32()?;
        let Some((model, n)) = model_by_id(model_id) else {
            return Err(ColmapError::UnknownModelId {
                path: path.to_path_buf(),
                record: c.record_name(),
                offset: at as u64,
                id: model_id,
            });
        };
        let width = c.u64()?;
        let height = c.u64()?;
        let params = (0..n).map(|_| c.f64()).collect::<Result<Vec<_>, _>>()?;
        Ok(ColmapCamera {
            id,
            model: model.to_string(),
            width,
            height,
            params,
        })
    })
}

/// `images.bin`: u32 id, f64 q[4], f64 t[3], u32 camera id, name + NUL, u64 n,
/// n × (f64 x, f64 y, u64 point3D id or u64::MAX).
pub(super) fn images(path: &Path) -> Result<Vec<ColmapImage>, ColmapError> {
    read(path, "image", 4 + 56 + 4 + 1 + 8, |c| {
        let id = c.u32()?;
        let at = c.pos;
        let qvec_wxyz = c.f64s::<4>()?;
        if !valid_quaternion(&qvec_wxyz) {
            return Err(c.error(
                at,
                format!("image {id}: quaternion {qvec_wxyz:?} is zero or not finite"),
            ));
        }
        let tvec = c.f64s::<3>()?;
        let camera_id = c.u32()?;
        let at = c.pos;
        let Some(len) = c.data[c.pos..].iter().position(|b| *b == 0) else {
            return Err(c.error(
                at,
                format!("image {id}: the name has no terminating NUL byte"),
            ));
        };
        let name = std::str::from_utf8(c.take(len)?)
            .map_err(|_| c.error(at, format!("image {id}: the name is not UTF-8")))?
            .to_string();
        c.take(1)?;
        let n = c.count(24, "points2D")?;
        let mut points2d = Vec::with_capacity(n);
        for _ in 0..n {
            let xy = c.f64s::<2>()?;
            let p = c.u64()?;
            points2d.push((xy, (p != NO_POINT).then_some(p)));
        }
        Ok(ColmapImage {
            id,
            name,
            camera_id,
            qvec_wxyz,
            tvec,
            points2d,
        })
    })
}

/// `points3D.bin`: u64 id, f64 xyz, u8 rgb, f64 error, u64 n, n × (u32 image id, u32 index).
pub(super) fn points(path: &Path) -> Result<Vec<ColmapPoint>, ColmapError> {
    read(path, "point", 8 + 24 + 3 + 8 + 8, |c| {
        let id = c.u64()?;
        let xyz = c.f64s::<3>()?;
        let rgb = c.array::<3>()?;
        let error = c.f64()?;
        let n = c.count(8, "track entries")?;
        let mut track = Vec::with_capacity(n);
        for _ in 0..n {
            track.push((c.u32()?, c.u32()?));
        }
        Ok(ColmapPoint {
            id,
            xyz,
            rgb,
            error,
            track,
        })
    })
}
