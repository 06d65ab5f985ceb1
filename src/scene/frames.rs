//! The `frames` table: one row per (camera, frame) image of the capture.

use std::path::Path;
use std::sync::Arc;

use arrow_array::builder::{FixedSizeListBuilder, Float64Builder};
use arrow_array::{
    Array, FixedSizeListArray, Float64Array, RecordBatch, StringArray, UInt16Array, UInt32Array,
};
use arrow_schema::{DataType, Field, Schema};

use super::table::{Table, TableError, column};

/// Whether a view is used for training or held out for evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Used to fit the scene.
    Train,
    /// Held out; scored by `evaluate`.
    Test,
}

impl Role {
    /// `train` / `test`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Train => "train",
            Self::Test => "test",
        }
    }
}

/// One image of the capture with its camera.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRow {
    /// Camera index.
    pub view: u16,
    /// Frame index (0-based; the background plate is not a row).
    pub frame: u16,
    /// Capture time, seconds.
    pub time_s: f64,
    /// 3×4 row-major `world_from_camera` in OpenCV camera axes (x right, y down, z forward);
    /// translation in metres (the camera centre).
    pub world_from_camera: [f64; 12],
    /// Focal lengths and principal point, pixels (pixel centres at i + 0.5).
    pub fx: f64,
    /// See `fx`.
    pub fy: f64,
    /// See `fx`.
    pub cx: f64,
    /// See `fx`.
    pub cy: f64,
    /// Image size, pixels.
    pub width: u32,
    /// See `width`.
    pub height: u32,
    /// White-composited object image, relative to the entry directory.
    pub image: String,
    /// Object mask (8-bit, 255 = object), relative to the entry directory.
    pub mask: String,
    /// The camera's background plate (the scene without the object), relative to the entry
    /// directory; `None` when the capture has none. Inside the mask the capture equals
    /// `image`; outside it equals the plate up to the object's shadow.
    pub plate: Option<String>,
    /// Train or test.
    pub role: Role,
}

/// The `frames` table.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Frames {
    /// Rows sorted by (view, frame).
    pub rows: Vec<FrameRow>,
}

fn f64_list(n: i32) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float64, false)), n)
}

impl Table for Frames {
    const NAME: &'static str = "frames";
    const VERSION: u32 = 2;

    fn schema() -> Schema {
        Schema::new(vec![
            Field::new("view", DataType::UInt16, false),
            Field::new("frame", DataType::UInt16, false),
            Field::new("time_s", DataType::Float64, false),
            Field::new("world_from_camera", f64_list(12), false),
            Field::new("fx", DataType::Float64, false),
            Field::new("fy", DataType::Float64, false),
            Field::new("cx", DataType::Float64, false),
            Field::new("cy", DataType::Float64, false),
            Field::new("width", DataType::UInt32, false),
            Field::new("height", DataType::UInt32, false),
            Field::new("image", DataType::Utf8, false),
            Field::new("mask", DataType::Utf8, false),
            Field::new("plate", DataType::Utf8, true),
            Field::new("role", DataType::Utf8, false),
        ])
        .with_metadata([
            ("schema_version".to_string(), Self::VERSION.to_string()),
            ("camera_convention".to_string(), "opencv".to_string()),
        ])
    }

    fn to_batch(&self) -> RecordBatch {
        let r = &self.rows;
        let mut m = FixedSizeListBuilder::new(Float64Builder::new(), 12)
            .with_field(Arc::new(Field::new("item", DataType::Float64, false)));
        for row in r {
            m.values().append_slice(&row.world_from_camera);
            m.append(true);
        }
        let f = |g: fn(&FrameRow) -> f64| Arc::new(Float64Array::from_iter_values(r.iter().map(g)));
        RecordBatch::try_new(
            Arc::new(Self::schema()),
            vec![
                Arc::new(UInt16Array::from_iter_values(r.iter().map(|x| x.view))),
                Arc::new(UInt16Array::from_iter_values(r.iter().map(|x| x.frame))),
                f(|x| x.time_s),
                Arc::new(m.finish()),
                f(|x| x.fx),
                f(|x| x.fy),
                f(|x| x.cx),
                f(|x| x.cy),
                Arc::new(UInt32Array::from_iter_values(r.iter().map(|x| x.width))),
                Arc::new(UInt32Array::from_iter_values(r.iter().map(|x| x.height))),
                Arc::new(StringArray::from_iter_values(
                    r.iter().map(|x| x.image.as_str()),
                )),
                Arc::new(StringArray::from_iter_values(
                    r.iter().map(|x| x.mask.as_str()),
                )),
                Arc::new(StringArray::from_iter(r.iter().map(|x| x.plate.as_deref()))),
                Arc::new(StringArray::from_iter_values(
                    r.iter().map(|x| x.role.as_str()),
                )),
            ],
        )
        .expect("columns match the schema")
    }

    fn from_batch(b: &RecordBatch, path: &Path) -> Result<Self, TableError> {
        let view = column::<UInt16Array>(b, "view");
        let frame = column::<UInt16Array>(b, "frame");
        let time = column::<Float64Array>(b, "time_s");
        let m = column::<FixedSizeListArray>(b, "world_from_camera");
        let mv = m
            .values()
            .as_any()
            .downcast_ref::<Float64Array>()
            .expect("checked type");
        let g = |n| column::<Float64Array>(b, n);
        let (fx, fy, cx, cy) = (g("fx"), g("fy"), g("cx"), g("cy"));
        let width = column::<UInt32Array>(b, "width");
        let height = column::<UInt32Array>(b, "height");
        let image = column::<StringArray>(b, "image");
        let mask = column::<StringArray>(b, "mask");
        let plate = column::<StringArray>(b, "plate");
        let role = column::<StringArray>(b, "role");
        let mut rows = Vec::with_capacity(b.num_rows());
        for i in 0..b.num_rows() {
            let mut w = [0.0; 12];
            w.copy_from_slice(&mv.values()[i * 12..i * 12 + 12]);
            let role = match role.value(i) {
                "train" => Role::Train,
                "test" => Role::Test,
                other => {
                    return Err(TableError::Invalid {
                        path: path.to_path_buf(),
                        message: format!("row {i}: role `{other}` is neither `train` nor `test`"),
                    });
                }
            };
            rows.push(FrameRow {
                view: view.value(i),
                frame: frame.value(i),
                time_s: time.value(i),
                world_from_camera: w,
                fx: fx.value(i),
                fy: fy.value(i),
                cx: cx.value(i),
                cy: cy.value(i),
                width: width.value(i),
                height: height.value(i),
                image: image.value(i).to_string(),
                mask: mask.value(i).to_string(),
                plate: plate.is_valid(i).then(|| plate.value(i).to_string()),
                role,
            });
        }
        debug_assert!(m.is_empty() || m.value_length() == 12);
        Ok(Self { rows })
    }
}
