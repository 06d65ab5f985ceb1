//! The `gaussians` table: 3D Gaussians (SoA), their splatting parameters and simulation flag.

use std::path::Path;
use std::sync::Arc;

use arrow_array::builder::{FixedSizeListBuilder, Float32Builder};
use arrow_array::{
    Array, BooleanArray, FixedSizeListArray, Float32Array, RecordBatch, UInt32Array,
};
use arrow_schema::{DataType, Field, Schema};

use super::table::{Table, TableError, column};

/// Number of SH coefficients per colour channel for degree `d`: (d + 1)².
pub fn sh_coeffs(degree: u8) -> usize {
    (degree as usize + 1).pow(2)
}

/// 3D Gaussians, structure of arrays (index i is one Gaussian in every field).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Gaussians {
    /// SH degree 0..=3.
    pub sh_degree: u8,
    /// Stable id (joins the `particles` table).
    pub id: Vec<u32>,
    /// Centre, metres (world).
    pub position: Vec<[f32; 3]>,
    /// Natural log of the standard deviations along the local axes (log metres).
    pub log_scale: Vec<[f32; 3]>,
    /// Rotation quaternion (w, x, y, z), not necessarily normalised.
    pub rotation: Vec<[f32; 4]>,
    /// Opacity logit: opacity = sigmoid(value).
    pub opacity_logit: Vec<f32>,
    /// SH coefficients, `[gaussian][coeff k][channel]`, 3·(deg+1)² per Gaussian.
    pub sh: Vec<f32>,
    /// Whether the Gaussian is a simulated particle (else rendered only).
    pub simulated: Vec<bool>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.id.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.id.is_empty()
    }
}

fn f32_list(n: i32) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float32, false)), n)
}

fn list_builder(n: i32) -> FixedSizeListBuilder<Float32Builder> {
    FixedSizeListBuilder::new(Float32Builder::new(), n).with_field(Arc::new(Field::new(
        "item",
        DataType::Float32,
        false,
    )))
}

impl Table for Gaussians {
    const NAME: &'static str = "gaussians";
    const VERSION: u32 = 1;

    fn schema() -> Schema {
        Schema::new(vec![
            Field::new("id", DataType::UInt32, false),
            Field::new("x", DataType::Float32, false),
            Field::new("y", DataType::Float32, false),
            Field::new("z", DataType::Float32, false),
            Field::new("log_scale", f32_list(3), false),
            Field::new("rot", f32_list(4), false),
            Field::new("opacity_logit", DataType::Float32, false),
            // Length 3·(deg+1)² depends on the file; -1 here means "checked against sh_degree".
            Field::new("sh", f32_list(-1), false),
            Field::new("simulated", DataType::Boolean, false),
        ])
        .with_metadata([
            ("schema_version".to_string(), Self::VERSION.to_string()),
            ("sh_layout".to_string(), "[coeff k][channel]".to_string()),
        ])
    }

    fn to_batch(&self) -> RecordBatch {
        let n_sh = 3 * sh_coeffs(self.sh_degree) as i32;
        let mut ls = list_builder(3);
        let mut rot = list_builder(4);
        let mut sh = list_builder(n_sh);
        for i in 0..self.len() {
            ls.values().append_slice(&self.log_scale[i]);
            ls.append(true);
            rot.values().append_slice(&self.rotation[i]);
            rot.append(true);
            sh.values()
                .append_slice(&self.sh[i * n_sh as usize..(i + 1) * n_sh as usize]);
            sh.append(true);
        }
        let mut schema = Self::schema();
        let mut fields: Vec<Field> = schema.fields().iter().map(|f| f.as_ref().clone()).collect();
        fields[7] = Field::new("sh", f32_list(n_sh), false);
        let mut md = schema.metadata().clone();
        md.insert("sh_degree", self.sh_degree.to_string());
        schema = Schema::new(fields).with_metadata(md);
        let p = |a: usize| {
            Arc::new(Float32Array::from_iter_values(
                self.position.iter().map(|v| v[a]),
            ))
        };
        RecordBatch::try_new(
            Arc::new(schema),
            vec![
                Arc::new(UInt32Array::from(self.id.clone())),
                p(0),
                p(1),
                p(2),
                Arc::new(ls.finish()),
                Arc::new(rot.finish()),
                Arc::new(Float32Array::from(self.opacity_logit.clone())),
                Arc::new(sh.finish()),
                Arc::new(BooleanArray::from(self.simulated.clone())),
            ],
        )
        .expect("columns match the schema")
    }

    fn from_batch(b: &RecordBatch, path: &Path) -> Result<Self, TableError> {
        let invalid = |message: String| TableError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        let degree: u8 = b
            .schema()
            .metadata()
            .get("sh_degree")
            .and_then(|s| s.parse().ok())
            .filter(|d| *d <= 3)
            .ok_or_else(|| invalid("metadata `sh_degree` missing or not in 0..=3".into()))?;
        let n_sh = 3 * sh_coeffs(degree);
        let sh = column::<FixedSizeListArray>(b, "sh");
        if sh.value_length() as usize != n_sh {
            return Err(invalid(format!(
                "column `sh` has {} values per Gaussian, SH degree {degree} needs {n_sh}",
                sh.value_length()
            )));
        }
        let vals = |a: &FixedSizeListArray| -> Vec<f32> {
            a.values()
                .as_any()
                .downcast_ref::<Float32Array>()
                .expect("checked type")
                .values()
                .to_vec()
        };
        let ls = vals(column::<FixedSizeListArray>(b, "log_scale"));
        let rot = vals(column::<FixedSizeListArray>(b, "rot"));
        let (x, y, z) = (
            column::<Float32Array>(b, "x"),
            column::<Float32Array>(b, "y"),
            column::<Float32Array>(b, "z"),
        );
        let n = b.num_rows();
        Ok(Self {
            sh_degree: degree,
            id: column::<UInt32Array>(b, "id").values().to_vec(),
            position: (0..n)
                .map(|i| [x.value(i), y.value(i), z.value(i)])
                .collect(),
            log_scale: ls.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
            rotation: rot
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            opacity_logit: column::<Float32Array>(b, "opacity_logit").values().to_vec(),
            sh: vals(sh),
            simulated: column::<BooleanArray>(b, "simulated")
                .iter()
                .map(|v| v.unwrap_or(false))
                .collect(),
        })
    }
}
