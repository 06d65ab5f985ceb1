//! `init` (visual hull of frame 0's masks, sampled to N Gaussians) on the fixture scene, then
//! `pipe export --format ply` and `pipe render` of the exported file: the hull must contain the
//! ground-truth particles of frame 0 (gt/particles/0.ply, PAC-NeRF's simulator state) and not be
//! much larger than the object, and the rendered silhouette must overlap the ground-truth mask.

use crate::support::{BuiltinRun, fixture_scene};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

use glam::{DVec3, IVec3};
use pipe::io::ply;
use pipe::scene::camera::Camera;
use pipe::scene::frames::{Frames, Role};
use pipe::scene::gaussians::Gaussians;
use pipe::scene::metrics::Metrics;
use pipe::scene::table;
use pipe::scene::visual_hull::{self, Hull, MaskedView};

fn fixture() -> PathBuf {
    fixture_scene()
}

/// The hull `init` carves from an ingest entry: frame 0's training views and their masks, at
/// `grid` voxels with `max_misses` views allowed to disagree (the same function and inputs).
fn carve_as_init(ingest: &Path, grid: usize, max_misses: usize) -> Hull {
    let frames: Frames = table::read(&ingest.join("frames.arrow")).unwrap();
    let rows: Vec<_> = frames
        .rows
        .iter()
        .filter(|r| r.frame == 0 && r.role == Role::Train)
        .collect();
    let cameras: Vec<Camera> = rows.iter().map(|r| Camera::from_row(r)).collect();
    let masks: Vec<Vec<u8>> = rows
        .iter()
        .map(|r| {
            pipe::io::image::read_gray8(&ingest.join(&r.mask))
                .unwrap()
                .2
        })
        .collect();
    let views: Vec<MaskedView> = cameras
        .iter()
        .zip(&masks)
        .map(|(camera, mask)| MaskedView { camera, mask })
        .collect();
    visual_hull::carve(&views, grid, max_misses)
}

/// A hull's voxels as integer indices from its box corner, and the index of the voxel holding
/// a point.
struct Voxels {
    set: HashSet<IVec3>,
    origin: DVec3,
    size: f64,
}

impl Voxels {
    fn of(hull: &Hull) -> Self {
        let mut v = Voxels {
            set: HashSet::new(),
            origin: hull.box_min,
            size: hull.voxel,
        };
        v.set = hull.centres.iter().map(|c| v.index(*c)).collect();
        v
    }
    fn index(&self, p: DVec3) -> IVec3 {
        ((p - self.origin) / self.size).floor().as_ivec3()
    }
    /// Whether `p` lies in a kept voxel.
    fn contains(&self, p: DVec3) -> bool {
        self.set.contains(&self.index(p))
    }
    /// Whether `p` lies within `k` voxels of a kept voxel (in it or in the cube of
    /// `(2k + 1)³` voxels around its own).
    fn near(&self, p: DVec3, k: i32) -> bool {
        let i = self.index(p);
        (-k..=k).any(|a| {
            (-k..=k).any(|b| (-k..=k).any(|c| self.set.contains(&(i + IVec3::new(a, b, c)))))
        })
    }
}

#[test]
fn visual_hull_init_contains_the_object_and_renders_its_silhouette() {
    let run = BuiltinRun::new(
        &fixture(),
        "[10]",
        "draft",
        "  ingest: {}\n  init: {points: 4000, seed: 7}\n",
    );
    run.run().unwrap();
    let (dir, file, reg) = (&run.dir, &run.file, pipe::stages::builtin());
    let entry = run.entry("init");
    let g: Gaussians = table::read(&entry.join("gaussians.arrow")).unwrap();
    assert_eq!(g.len(), 4000);
    assert_eq!(g.sh_degree, 1, "draft preset");
    assert!(g.simulated.iter().all(|s| *s));

    // Ground truth: PAC-NeRF's particles at frame 0 (14137 particles of 1e-6 m³).
    let gt = ply::read_points(&fixture().join("gt/particles/0.ply")).unwrap();
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in &gt.positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    // The hull contains the object. Carved again from the ingest masks with init's function
    // and parameters (draft: 96 voxels; max_misses 1), it is init's hull: same voxel count and
    // volume as its metrics, and every Gaussian lies in one of its voxels. PAC-NeRF's particles
    // of frame 0 lie in it but for a surface layer: a voxel (6.2 mm) whose centre projects just
    // outside two masks is carved although part of it is object, and the matte's own errors
    // (IoU ~0.95) carve more. Tolerance: ≥ 97 % of the particles in the hull (measured
    // 97.07 %), every one within two voxels of it (measured: all but 10 within one).
    let hull = carve_as_init(&run.entry("ingest"), 96, 1);
    let voxels = Voxels::of(&hull);
    let m: Metrics = table::read(&entry.join("metrics.arrow")).unwrap();
    let metric = |name: &str| m.rows.iter().find(|r| r.metric == name).unwrap().value;
    assert_eq!(metric("hull_voxels"), hull.centres.len() as f64);
    assert_eq!(metric("hull_volume_m3"), hull.volume());
    let in_hull = |points: &[[f32; 3]]| {
        points
            .iter()
            .filter(|p| voxels.contains(DVec3::from_array(p.map(f64::from))))
            .count() as f64
            / points.len() as f64
    };
    assert!(in_hull(&g.position) >= 0.999, "{}", in_hull(&g.position));
    let inside = in_hull(&gt.positions);
    let near = |k| {
        gt.positions
            .iter()
            .filter(|p| voxels.near(DVec3::from_array(p.map(f64::from)), k))
            .count()
    };
    let (near1, near2) = (near(1), near(2));
    println!(
        "ground-truth particles in the hull: {:.2} %; within one voxel ({:.1} mm) {near1}, within two {near2}, of {}",
        100.0 * inside,
        hull.voxel * 1e3,
        gt.positions.len()
    );
    assert!(
        inside >= 0.97,
        "{:.2} % of the particles in the hull",
        100.0 * inside
    );
    assert_eq!(
        near2,
        gt.positions.len(),
        "every particle within two voxels"
    );

    // The hull is not much larger than the object: every Gaussian lies within the object's
    // box grown by 3 cm.
    for x in &g.position {
        for a in 0..3 {
            assert!(
                x[a] > lo[a] - 0.03 && x[a] < hi[a] + 0.03,
                "{x:?} outside {lo:?}..{hi:?}"
            );
        }
    }
    let volume = metric("hull_volume_m3");
    let object = gt.positions.len() as f64 * 1e-6;
    assert!(
        volume > object && volume < 1.6 * object,
        "hull {volume} m³ vs object {object} m³"
    );
    // The colours are the torus' (red/yellow stripes): red dominates blue on average.
    let k = 3 * pipe::scene::gaussians::sh_coeffs(g.sh_degree);
    let mean_dc: Vec<f32> = (0..3)
        .map(|c| g.sh.chunks(k).map(|s| s[c]).sum::<f32>() / g.len() as f32)
        .collect();
    assert!(mean_dc[0] > mean_dc[2] + 0.3, "{mean_dc:?}");

    // Export to PLY and render it from camera 3 with the CLI.
    let out_ply = dir.path().join("init.ply");
    let code = pipe::cli::run(
        [
            "pipe",
            "--workdir",
            dir.path().to_str().unwrap(),
            "export",
            file.to_str().unwrap(),
            "--stage",
            "init",
            "--format",
            "ply",
            "--out",
            out_ply.to_str().unwrap(),
        ],
        reg.clone(),
    );
    assert_eq!(code, 0);
    let png = dir.path().join("v3.png");
    let exr = dir.path().join("v3.exr");
    let cams = fixture().join("all_data.json");
    let code = pipe::cli::run(
        [
            "pipe",
            "render",
            out_ply.to_str().unwrap(),
            "--cameras",
            cams.to_str().unwrap(),
            "--view",
            "3",
            "--out",
            png.to_str().unwrap(),
            "--depth",
            exr.to_str().unwrap(),
            "--background",
            "0,0,0.5",
        ],
        reg.clone(),
    );
    assert_eq!(code, 0);
    assert!(exr.metadata().unwrap().len() > 0);
    let img = image::open(&png).unwrap().into_rgb8();
    assert_eq!(img.dimensions(), (100, 100));
    assert_eq!(
        img.get_pixel(0, 0).0,
        [0, 0, 128],
        "the --background colour"
    );
    for bad in ["1,1", "1,1,1,1"] {
        let code = pipe::cli::run(
            [
                "pipe",
                "render",
                out_ply.to_str().unwrap(),
                "--cameras",
                cams.to_str().unwrap(),
            ]
            .into_iter()
            .chain([
                "--view",
                "3",
                "--out",
                png.to_str().unwrap(),
                "--background",
                bad,
            ]),
            reg.clone(),
        );
        assert_ne!(code, 0, "--background {bad}");
    }
    let gt_mask = image::open(fixture().join("gt/masks/m_3_0.png"))
        .unwrap()
        .into_luma8();
    let (mut inter, mut union) = (0u32, 0u32);
    for (px, m) in img.pixels().zip(gt_mask.pixels()) {
        let [r, g, b] = px.0.map(i32::from);
        let ours = r > 55 || g > 55 || (b - 128).abs() > 55;
        let theirs = m.0[0] >= 128;
        inter += u32::from(ours && theirs);
        union += u32::from(ours || theirs);
    }
    let iou = f64::from(inter) / f64::from(union);
    assert!(
        iou > 0.6,
        "silhouette IoU of the initial Gaussians {iou:.3}"
    );
}

fn run_init(init: &str) -> Result<Gaussians, String> {
    let run = BuiltinRun::new(
        &fixture(),
        "[10]",
        "standard",
        &format!("  ingest: {{frames: [0]}}\n  init: {init}\n"),
    );
    run.run()?;
    Ok(table::read(&run.entry("init").join("gaussians.arrow")).unwrap())
}

#[test]
fn init_from_a_ply_subsamples_and_sizes_by_the_nearest_neighbour() {
    let g =
        run_init("{source: ply, path: gt/particles/0.ply, points: 2000, sh_degree: 0}").unwrap();
    assert_eq!(g.len(), 2000);
    let gt = ply::read_points(&fixture().join("gt/particles/0.ply")).unwrap();
    // Every Gaussian is one of the file's points.
    let set: std::collections::HashSet<[u32; 3]> =
        gt.positions.iter().map(|p| p.map(f32::to_bits)).collect();
    assert!(
        g.position
            .iter()
            .all(|p| set.contains(&p.map(f32::to_bits)))
    );
    // 2000 of 14137 points in ~14 L: neighbours ~1–3 cm apart.
    let s: Vec<f32> = g.log_scale.iter().map(|l| l[0].exp()).collect();
    let mean = s.iter().sum::<f32>() / s.len() as f32;
    assert!(mean > 0.004 && mean < 0.03, "mean scale {mean}");
    // The file has no colours: grey, i.e. SH DC 0.
    assert!(g.sh.iter().all(|v| *v == 0.0));
}

#[test]
fn init_from_colmap_keeps_every_point_and_its_colour() {
    let colmap =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/formats/colmap/sparse/0");
    let g = run_init(&format!(
        "{{source: colmap, path: {}, sh_degree: 0}}",
        colmap.display()
    ))
    .unwrap();
    assert_eq!(g.len(), 50);
    let m = pipe::io::colmap::read_model(&colmap).unwrap();
    for (i, pt) in m.points.iter().enumerate() {
        assert_eq!(g.position[i], pt.xyz.map(|v| v as f32));
        let rgb = g.sh[i * 3..i * 3 + 3]
            .iter()
            .map(|d| d * 0.282_094_8 + 0.5)
            .collect::<Vec<f32>>();
        for (got, want) in rgb.iter().zip(pt.rgb) {
            assert!((got - f32::from(want) / 255.0).abs() < 1e-5);
        }
    }
}

#[test]
fn init_source_and_path_must_agree() {
    let e = run_init("{source: ply}").unwrap_err();
    assert!(
        e.contains("stages.init.path: is required with `source: ply`"),
        "{e}"
    );
    let e = run_init("{path: x.ply}").unwrap_err();
    assert!(e.contains("stages.init.path: is only used with"), "{e}");
    let e = run_init("{source: ply, path: nope.ply}").unwrap_err();
    assert!(e.contains("nope.ply is not a file"), "{e}");
    let e = run_init("{source: dataset, path: x.ply}").unwrap_err();
    assert!(e.contains("stages.init.path: is only used with"), "{e}");
    // A PAC-NeRF scene has no trained Gaussians.
    let e = run_init("{source: dataset}").unwrap_err();
    assert!(
        e.contains("stages.init.source: `dataset` takes the dataset's trained Gaussians, and the `pacnerf` layout has none"),
        "{e}"
    );
}
