//! Arrow tables round-trip exactly, reading a file whose schema differs names the missing or
//! mistyped column, and the schema contracts in `schemas/` match the code.

use std::path::Path;
use std::sync::Arc;

use arrow_array::{Float32Array, RecordBatch, UInt16Array};
use arrow_schema::{DataType, Field, Schema};
use pipe::pipeline::stage::MetricRow;
use pipe::scene::frames::{FrameRow, Frames, Role};
use pipe::scene::gaussians::Gaussians;
use pipe::scene::metrics::Metrics;
use pipe::scene::table::{self, Table, TableError};
use pipe::simulate::Trajectories;

fn frames() -> Frames {
    Frames {
        rows: (0..3)
            .map(|i| FrameRow {
                view: i,
                frame: 2 * i,
                time_s: f64::from(i) / 24.0,
                world_from_camera: std::array::from_fn(|k| k as f64 * 0.5 + f64::from(i)),
                fx: 100.5,
                fy: 101.5,
                cx: 50.0,
                cy: 49.0,
                width: 100,
                height: 98,
                image: format!("images/r_{i}.png"),
                mask: format!("masks/m_{i}.png"),
                plate: (i != 1).then(|| format!("plates/p_{i}.png")),
                role: if i == 2 { Role::Test } else { Role::Train },
            })
            .collect(),
    }
}

#[test]
fn tables_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let f = frames();
    table::write(&dir.path().join("frames.arrow"), &f).unwrap();
    assert_eq!(
        table::read::<Frames>(&dir.path().join("frames.arrow")).unwrap(),
        f
    );

    for degree in 0..=3u8 {
        let n = 5;
        let k = 3 * pipe::scene::gaussians::sh_coeffs(degree);
        let g = Gaussians {
            sh_degree: degree,
            id: (0..n as u32).collect(),
            position: (0..n).map(|i| [i as f32, -(i as f32), 0.5]).collect(),
            log_scale: (0..n).map(|i| [-(i as f32), -2.0, -3.0]).collect(),
            rotation: (0..n).map(|i| [1.0, 0.0, i as f32, 0.0]).collect(),
            opacity_logit: (0..n).map(|i| i as f32 - 2.0).collect(),
            sh: (0..n * k).map(|i| i as f32 * 0.01).collect(),
            simulated: (0..n).map(|i| i % 2 == 0).collect(),
        };
        let p = dir.path().join(format!("g{degree}.arrow"));
        table::write(&p, &g).unwrap();
        assert_eq!(table::read::<Gaussians>(&p).unwrap(), g);
    }

    let m = Metrics {
        stage: "warmup".into(),
        rows: vec![
            MetricRow {
                epoch: Some(3),
                view: None,
                frame: Some(0),
                metric: "psnr".into(),
                value: 31.5,
            },
            MetricRow {
                epoch: None,
                view: Some(10),
                frame: None,
                metric: "ssim".into(),
                value: 0.97,
            },
        ],
    };
    table::write(&dir.path().join("m.arrow"), &m).unwrap();
    assert_eq!(
        table::read::<Metrics>(&dir.path().join("m.arrow")).unwrap(),
        m
    );
}

/// A table written in parts (`particles.arrow`, one batch per frame) reads back as the
/// concatenation of its parts; a writer dropped unfinished leaves no file at all, not even its
/// temporary.
#[test]
fn a_table_written_in_parts() {
    let dir = tempfile::tempdir().unwrap();
    let x = |k: f32| vec![[k, 2.0 * k, -k], [0.5, k, 1.0]];
    let v = |k: f32| vec![[k; 3], [-k, 0.0, 3.0]];
    let path = dir.path().join("particles.arrow");

    let mut w = table::Writer::<Trajectories>::create(&path).unwrap();
    w.write(&Trajectories::frame_batch(0, &x(0.0), &v(0.0)))
        .unwrap();
    drop(w);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);

    let mut w = table::Writer::<Trajectories>::create(&path).unwrap();
    for k in 0..3u16 {
        let kf = f32::from(k);
        w.write(&Trajectories::frame_batch(k, &x(kf), &v(kf)))
            .unwrap();
    }
    assert!(!path.exists(), "the table appears only when finished");
    w.finish().unwrap();
    let batches = arrow_ipc::reader::FileReader::try_new(std::fs::File::open(&path).unwrap(), None)
        .unwrap()
        .count();
    assert_eq!(batches, 3);
    let t = table::read::<Trajectories>(&path).unwrap();
    assert_eq!(t.frame, [0, 0, 1, 1, 2, 2]);
    assert_eq!(t.id, [0, 1, 0, 1, 0, 1]);
    assert_eq!(t.positions(2), x(2.0));
    assert_eq!(t.v[2..4], v(1.0));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

fn write_batch(path: &Path, batch: &RecordBatch) {
    let file = std::fs::File::create(path).unwrap();
    let mut w = arrow_ipc::writer::FileWriter::try_new(file, &batch.schema()).unwrap();
    w.write(batch).unwrap();
    w.finish().unwrap();
}

#[test]
fn schema_mismatch_names_the_column() {
    let dir = tempfile::tempdir().unwrap();
    // A `frames` file whose `fx` is missing.
    let full = frames().to_batch();
    let keep: Vec<usize> = (0..full.num_columns())
        .filter(|&i| full.schema().field(i).name() != "fx")
        .collect();
    let p = dir.path().join("no_fx.arrow");
    write_batch(&p, &full.project(&keep).unwrap());
    match table::read::<Frames>(&p) {
        Err(e @ TableError::MissingColumn { .. }) => {
            assert!(
                e.to_string()
                    .contains("column `fx` is missing (expected Float64)"),
                "{e}"
            )
        }
        other => panic!("expected a missing column, got {other:?}"),
    }
    // `view` stored as f32 instead of u16.
    let schema = Schema::new(vec![Field::new("view", DataType::Float32, false)]);
    let b = RecordBatch::try_new(
        Arc::new(schema),
        vec![Arc::new(Float32Array::from(vec![1.0f32]))],
    )
    .unwrap();
    let p = dir.path().join("bad_view.arrow");
    write_batch(&p, &b);
    let e = table::read::<Frames>(&p).unwrap_err().to_string();
    assert!(
        e.contains("column `view` has type Float32, expected UInt16"),
        "{e}"
    );
    // Not an Arrow file at all.
    let p = dir.path().join("junk.arrow");
    std::fs::write(&p, b"not arrow").unwrap();
    let e = table::read::<Frames>(&p).unwrap_err().to_string();
    assert!(
        e.contains("junk.arrow: not a readable Arrow IPC file"),
        "{e}"
    );
    let _ = UInt16Array::from(vec![1u16]);
}

#[test]
fn committed_table_schemas_match_the_code() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas");
    for (name, json) in [
        ("frames", table::schema_json::<Frames>()),
        ("gaussians", table::schema_json::<Gaussians>()),
        ("metrics", table::schema_json::<Metrics>()),
        (
            "field_weights",
            table::schema_json::<pipe::physics::material_field::FieldTable>(),
        ),
        (
            "material_particles",
            table::schema_json::<pipe::physics::particles::MaterialParticles>(),
        ),
    ] {
        let path = root.join(format!("{name}.arrow.json"));
        let text = serde_json::to_string_pretty(&json).unwrap() + "\n";
        if std::env::var_os("PIPE_WRITE_SCHEMAS").is_some() {
            std::fs::write(&path, &text).unwrap();
        }
        assert_eq!(
            std::fs::read_to_string(&path).unwrap_or_default(),
            text,
            "{} is out of date; regenerate with PIPE_WRITE_SCHEMAS=1 cargo test -p pipe --test cli schemas",
            path.display()
        );
    }
}
