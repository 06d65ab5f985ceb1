//! Stage `init`: the initial Gaussians of the object.
//!
//! Default source: space carving of one frame's masks over all training views (the object's
//! visual hull), sampled uniformly to the requested count, coloured by the per-channel median
//! of the pixels it projects to. Scales start isotropic at half the mean point spacing
//! ((V/N)^(1/3) / 2), rotations at identity, opacities at 0.1 (3DGS's initial value).
//!
//! Other sources: a point-cloud or 3DGS PLY, or a COLMAP sparse model (`.bin` or `.txt`), in
//! the scene's world frame (metres). Their points are used as they are (a seeded random subset
//! when there are more than `points`), coloured from the file (grey when it has no colours),
//! with isotropic scales at the distance to the nearest other point, as 3DGS initialises.
//!
//! `source: dataset`: a layout that ships trained Gaussians (PhysDreamer's `point_cloud.ply`)
//! gives them as they are, with the moving part marked `simulated` by `ingest`.

use std::path::PathBuf;

use glam::DVec3;
use rand::{Rng, SeedableRng};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::io::image;
use crate::pipeline::spec::Preset;
use crate::pipeline::spec::SceneSpec;
use crate::pipeline::stage::{
    InputFile, MetricRow, ParamError, StageContext, StageError, TypedStage,
};
use crate::scene::camera::Camera;
use crate::scene::frames::{Frames, Role};
use crate::scene::gaussians::{Gaussians, sh_coeffs};
use crate::scene::table::{self, Table};
use crate::scene::visual_hull::{self, MaskedView};

/// Zeroth SH basis constant Y₀₀ = 1 / (2√π).
pub const SH_C0: f32 = 0.282_094_8;

/// Where the initial Gaussians come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum InitSource {
    /// Space carving of the masks (needs no other input).
    VisualHull,
    /// A point-cloud or 3DGS PLY named by `path`.
    Ply,
    /// A COLMAP sparse model folder (`cameras`, `images`, `points3D` as .bin or .txt) named by
    /// `path`.
    Colmap,
    /// The dataset's trained Gaussians as they are (`scene.dataset: physdreamer`:
    /// `point_cloud.ply`, the moving part marked `simulated` by `ingest`); `points`,
    /// `sh_degree`, `opacity` and `seed` do not apply.
    Dataset,
}

/// Parameters of `init`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct InitParams {
    /// Where the points come from.
    #[serde(default = "default_source")]
    pub source: InitSource,
    /// The PLY file or COLMAP folder for `source: ply | colmap`; relative paths are relative to
    /// the scene folder.
    #[serde(default)]
    pub path: Option<PathBuf>,
    /// Number of Gaussians to create.
    #[serde(default = "default_points")]
    pub points: u32,
    /// Frame whose masks are carved.
    #[serde(default)]
    pub frame: u16,
    /// Carving voxels along the longest edge of the box.
    #[serde(default = "default_grid")]
    pub grid: u32,
    /// Views allowed to disagree (robustness to matte errors).
    #[serde(default = "default_misses")]
    pub max_misses: u32,
    /// SH degree of the created Gaussians (higher coefficients start at zero).
    #[serde(default = "default_sh")]
    pub sh_degree: u8,
    /// Initial opacity in (0, 1).
    #[serde(default = "default_opacity")]
    pub opacity: f32,
    /// Random seed of the sampling.
    #[serde(default)]
    pub seed: u64,
}

fn default_source() -> InitSource {
    InitSource::VisualHull
}
fn default_points() -> u32 {
    20_000
}
fn default_grid() -> u32 {
    128
}
fn default_misses() -> u32 {
    1
}
fn default_sh() -> u8 {
    3
}
fn default_opacity() -> f32 {
    0.1
}

/// Problems specific to init.
#[derive(Debug, thiserror::Error)]
pub enum InitError {
    /// Reading the upstream table failed.
    #[error(transparent)]
    Table(#[from] table::TableError),
    /// Reading a mask or image failed.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// The data cannot produce Gaussians.
    #[error("{0}")]
    Invalid(String),
}

/// The `init` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Init;

impl TypedStage for Init {
    type Params = InitParams;
    const KIND: &'static str = "init";
    // 3: the carving box holds what the cameras look at (it spanned only their centres, which
    // cut objects below every camera: frames after the first landed outside it).
    const VERSION: u32 = 3;
    const DESCRIPTION: &'static str = "Initial Gaussians of the object: visual hull of one frame's masks, sampled and coloured from the images";
    const UPSTREAM: &'static [&'static str] = &["ingest"];

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        vec![(Gaussians::NAME, Gaussians::VERSION)]
    }

    fn preset_params(&self, preset: Preset) -> Value {
        match preset {
            Preset::Draft => json!({"points": 3000, "grid": 96, "sh_degree": 1}),
            Preset::Standard => json!({"points": 20000, "grid": 128}),
            Preset::Paper => json!({"points": 50000, "grid": 192}),
        }
    }

    fn validate(&self, p: &InitParams) -> Result<(), ParamError> {
        let bad = |path: &str, message: String| {
            Err(ParamError {
                path: path.into(),
                message,
            })
        };
        if p.points == 0 {
            return bad("points", "must be at least 1".into());
        }
        if p.sh_degree > 3 {
            return bad("sh_degree", format!("must be 0..=3, found {}", p.sh_degree));
        }
        if !(p.opacity > 0.0 && p.opacity < 1.0) {
            return bad("opacity", format!("must be in (0, 1), found {}", p.opacity));
        }
        if !(8..=1024).contains(&p.grid) {
            return bad("grid", format!("must be in 8..=1024, found {}", p.grid));
        }
        match (p.source, &p.path) {
            (InitSource::VisualHull | InitSource::Dataset, Some(_)) => bad(
                "path",
                "is only used with `source: ply` or `source: colmap`".into(),
            ),
            (InitSource::Ply | InitSource::Colmap, None) => bad(
                "path",
                "is required with `source: ply` or `source: colmap`".into(),
            ),
            _ => Ok(()),
        }
    }

    fn inputs(&self, p: &InitParams, scene: &SceneSpec) -> Result<Vec<InputFile>, StageError> {
        let Some(path) = p.path.as_ref() else {
            return Ok(Vec::new());
        };
        let full = scene.path.join(path);
        let missing = |what: String| StageError::failed(InitError::Invalid(what));
        match p.source {
            InitSource::VisualHull | InitSource::Dataset => Ok(Vec::new()),
            InitSource::Ply => {
                if !full.is_file() {
                    return Err(missing(format!(
                        "stages.init.path: {} is not a file",
                        full.display()
                    )));
                }
                Ok(vec![InputFile {
                    logical_name: "points.ply".into(),
                    path: full,
                }])
            }
            InitSource::Colmap => {
                let files: Vec<InputFile> = ["cameras", "images", "points3D"]
                    .iter()
                    .flat_map(|stem| ["bin", "txt"].map(|ext| format!("{stem}.{ext}")))
                    .filter(|name| full.join(name).is_file())
                    .map(|name| InputFile {
                        path: full.join(&name),
                        logical_name: format!("colmap/{name}"),
                    })
                    .collect();
                if files.is_empty() {
                    return Err(missing(format!(
                        "stages.init.path: {} holds no COLMAP model (cameras/images/points3D .bin or .txt)",
                        full.display()
                    )));
                }
                Ok(files)
            }
        }
    }

    fn run(&self, p: &InitParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        match p.source {
            InitSource::VisualHull => {}
            InitSource::Dataset => return from_dataset(ctx),
            InitSource::Ply | InitSource::Colmap => return from_points(p, ctx),
        }
        let ingest = ctx.upstream("ingest")?.dir.clone();
        let frames: Frames =
            table::read(&ingest.join("frames.arrow")).map_err(StageError::failed)?;
        let rows: Vec<_> = frames
            .rows
            .iter()
            .filter(|r| r.frame == p.frame && r.role == Role::Train)
            .collect();
        if rows.len() < 2 {
            return Err(StageError::failed(InitError::Invalid(format!(
                "stages.init.frame: frame {} has {} training view(s); carving needs at least 2",
                p.frame,
                rows.len()
            ))));
        }
        let cameras: Vec<Camera> = rows.iter().map(|r| Camera::from_row(r)).collect();
        let load = |rel: &str| -> Result<(PathBuf, Vec<u8>), StageError> {
            let path = ingest.join(rel);
            let (_, _, m) = image::read_gray8(&path).map_err(StageError::failed)?;
            Ok((path, m))
        };
        let masks: Vec<Vec<u8>> = rows
            .iter()
            .map(|r| load(&r.mask).map(|x| x.1))
            .collect::<Result<_, _>>()?;
        let images: Vec<image::Rgb8> = rows
            .iter()
            .map(|r| image::read_rgb8(&ingest.join(&r.image)).map_err(StageError::failed))
            .collect::<Result<_, _>>()?;
        ctx.check_interrupted()?;
        let views: Vec<MaskedView> = cameras
            .iter()
            .zip(&masks)
            .map(|(c, m)| MaskedView { camera: c, mask: m })
            .collect();
        let hull = visual_hull::carve(&views, p.grid as usize, p.max_misses as usize);
        if hull.centres.is_empty() {
            return Err(StageError::failed(InitError::Invalid(format!(
                "the visual hull of frame {} is empty: the masks of its {} training views do not agree on any point (check the ingest masks in {})",
                p.frame,
                rows.len(),
                ingest.join("masks").display()
            ))));
        }
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(p.seed);
        let n = p.points as usize;
        let positions: Vec<DVec3> = (0..n)
            .map(|_| {
                let c = hull.centres[rng.random_range(0..hull.centres.len())];
                let j = DVec3::new(
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                ) - 0.5;
                c + j * hull.voxel
            })
            .collect();
        let spacing = (hull.volume() / n as f64).cbrt();
        let log_scale = (0.5 * spacing).ln() as f32;
        let k = sh_coeffs(p.sh_degree);
        let mut sh = vec![0.0f32; n * k * 3];
        for (i, x) in positions.iter().enumerate() {
            let rgb = median_colour(*x, &cameras, &masks, &images);
            for c in 0..3 {
                sh[i * k * 3 + c] = (rgb[c] - 0.5) / SH_C0;
            }
        }
        let opacity_logit = (p.opacity / (1.0 - p.opacity)).ln();
        let g = Gaussians {
            sh_degree: p.sh_degree,
            id: (0..n as u32).collect(),
            position: positions.iter().map(|x| x.as_vec3().to_array()).collect(),
            log_scale: vec![[log_scale; 3]; n],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacity_logit: vec![opacity_logit; n],
            sh,
            simulated: vec![true; n],
        };
        table::write(&ctx.out_dir.join("gaussians.arrow"), &g).map_err(StageError::failed)?;
        let (lo, hi) = hull.bounds().expect("non-empty");
        ctx.progress.log(&format!(
            "visual hull of frame {}: {} voxels of {:.1} mm, {:.3} L, bounds [{:.3}, {:.3}, {:.3}]–[{:.3}, {:.3}, {:.3}] m; {n} Gaussians",
            p.frame,
            hull.centres.len(),
            hull.voxel * 1e3,
            hull.volume() * 1e3,
            lo.x,
            lo.y,
            lo.z,
            hi.x,
            hi.y,
            hi.z
        ));
        for (metric, value) in [
            ("hull_volume_m3", hull.volume()),
            ("hull_voxels", hull.centres.len() as f64),
            ("gaussians", n as f64),
        ] {
            ctx.metric(MetricRow {
                epoch: None,
                view: None,
                frame: Some(p.frame),
                metric: metric.into(),
                value,
            });
        }
        Ok(())
    }
}

/// Gaussians from a PLY or COLMAP point set.
fn from_points(p: &InitParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
    let path = ctx.scene.path.join(p.path.as_ref().expect("validated"));
    let (positions, colours): (Vec<[f32; 3]>, Option<Vec<[f32; 3]>>) = match p.source {
        InitSource::Ply => {
            let pc = crate::io::ply::read_points(&path).map_err(StageError::failed)?;
            (pc.positions, pc.colors)
        }
        InitSource::Colmap => {
            let m = crate::io::colmap::read_model(&path).map_err(StageError::failed)?;
            (
                m.points.iter().map(|q| q.xyz.map(|v| v as f32)).collect(),
                Some(
                    m.points
                        .iter()
                        .map(|q| q.rgb.map(|c| f32::from(c) / 255.0))
                        .collect(),
                ),
            )
        }
        InitSource::VisualHull | InitSource::Dataset => unreachable!("handled by the caller"),
    };
    if positions.is_empty() {
        return Err(StageError::failed(InitError::Invalid(format!(
            "{}: holds no points",
            path.display()
        ))));
    }
    let mut order: Vec<usize> = (0..positions.len()).collect();
    if order.len() > p.points as usize {
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(p.seed);
        rand::seq::SliceRandom::shuffle(order.as_mut_slice(), &mut rng);
        order.truncate(p.points as usize);
        order.sort_unstable();
    }
    let pts: Vec<DVec3> = order
        .iter()
        .map(|&i| DVec3::from(positions[i].map(f64::from)))
        .collect();
    let bounds = crate::scene::neighbors::bounds(&pts).expect("non-empty");
    let extent = (bounds.1 - bounds.0).max_element().max(1e-6);
    let grid =
        crate::scene::neighbors::PointGrid::new(&pts, extent / (pts.len() as f64).cbrt().max(1.0));
    let n = pts.len();
    let k = sh_coeffs(p.sh_degree);
    let mut sh = vec![0.0f32; n * k * 3];
    let mut log_scale = Vec::with_capacity(n);
    for (j, &i) in order.iter().enumerate() {
        let rgb = colours.as_ref().map_or([0.5; 3], |c| c[i]);
        for c in 0..3 {
            sh[j * k * 3 + c] = (rgb[c] - 0.5) / SH_C0;
        }
        let d = grid
            .nearest(pts[j], Some(j))
            .map_or(extent * 0.01, |(_, d)| d)
            .max(1e-7);
        log_scale.push([(d as f32).ln(); 3]);
    }
    let opacity_logit = (p.opacity / (1.0 - p.opacity)).ln();
    let g = Gaussians {
        sh_degree: p.sh_degree,
        id: (0..n as u32).collect(),
        position: pts.iter().map(|x| x.as_vec3().to_array()).collect(),
        log_scale,
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
        opacity_logit: vec![opacity_logit; n],
        sh,
        simulated: vec![true; n],
    };
    table::write(&ctx.out_dir.join("gaussians.arrow"), &g).map_err(StageError::failed)?;
    ctx.progress.log(&format!(
        "{n} Gaussians from {} ({} points in the file)",
        path.display(),
        positions.len()
    ));
    ctx.metric(MetricRow::of_stage("gaussians", n as f64));
    Ok(())
}

/// The trained Gaussians `ingest` read from the dataset, as they are.
fn from_dataset(ctx: &mut StageContext<'_>) -> Result<(), StageError> {
    let ingest = ctx.upstream("ingest")?.dir.clone();
    let path = ingest.join(crate::stages::ingest::trained::GAUSSIANS);
    if !path.is_file() {
        return Err(StageError::failed(InitError::Invalid(format!(
            "stages.init.source: `dataset` takes the dataset's trained Gaussians, and the `{}` \
             layout has none (only `physdreamer` has: point_cloud.ply); use `visual_hull`, \
             `ply` or `colmap`",
            ctx.scene.dataset.name()
        ))));
    }
    let g: Gaussians = table::read(&path).map_err(StageError::failed)?;
    table::write(&ctx.out_dir.join("gaussians.arrow"), &g).map_err(StageError::failed)?;
    let moving = g.simulated.iter().filter(|s| **s).count();
    ctx.progress.log(&format!(
        "{} trained Gaussians of the dataset (SH degree {}), {moving} simulated, {} held in place",
        g.len(),
        g.sh_degree,
        g.len() - moving
    ));
    ctx.metric(MetricRow::of_stage("gaussians", g.len() as f64));
    Ok(())
}

/// Per-channel median colour (in [0, 1]) of the pixels `x` projects to inside the masks.
fn median_colour(
    x: DVec3,
    cameras: &[Camera],
    masks: &[Vec<u8>],
    images: &[image::Rgb8],
) -> [f32; 3] {
    let mut samples: [Vec<u8>; 3] = Default::default();
    for ((cam, mask), img) in cameras.iter().zip(masks).zip(images) {
        if let Some((u, v)) = cam.pixel(x) {
            let i = (v * cam.width + u) as usize;
            if mask[i] >= 128 {
                for (c, s) in samples.iter_mut().enumerate() {
                    s.push(img.data[i * 3 + c]);
                }
            }
        }
    }
    samples.map(|mut s| {
        if s.is_empty() {
            0.5
        } else {
            let mid = s.len() / 2;
            let (_, m, _) = s.select_nth_unstable(mid);
            f32::from(*m) / 255.0
        }
    })
}
