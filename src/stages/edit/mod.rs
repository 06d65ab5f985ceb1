//! Stage `edit`: new motion of the learned scene (the seed paper's §4.3.2): push, pull, drop,
//! stiffen or soften the object and watch it from any viewpoint.
//!
//! `edit:` in a pipeline file maps names to edits; each is a stage `edit.<name>` with its own
//! parameters ([`params::EditParams`]) and cache entry, so changing one edit re-runs only it,
//! and all of them share the upstream entries. An edit reads the canonical Gaussians
//! (`warmup`'s, else `init`'s: a PhysDreamer scene's trained Gaussians need no warm-up), the
//! capture's cameras and frame interval (`ingest`) and, when the pipeline has
//! them, the learned material (`material`) and initial velocity (`velocity`, else
//! `material.json`'s); without a `material` stage its `material:` block gives the material.
//!
//! The object is built as the physics stages build theirs ([`crate::physics::object`]: the
//! Gaussians that simulate become particles, a closed splat surface is filled inside) with the
//! edit's material, gravity and boundaries; Gaussians marked as not simulated (`simulated`
//! false: a scene's static part) are rendered where they are. The forces and impulses are the
//! engine's ([`select`]: a total vector spread by mass over the selected material); the frame
//! loop is `pipe simulate`'s ([`crate::simulate::run_frames`]): every frame's substeps follow
//! the stability limit at the speed its forces can give, NaN/Inf stops with the engine's
//! error, particles are never dropped and the declared boundaries' contacts are counted.
//!
//! Writes into its entry: `edit.json` ([`EditReport`]), `renders/<camera>/NNNN.png` per
//! camera and frame, `renders/<camera>.gif`, `renders/<camera>.mp4` when `ffmpeg` is on
//! `PATH`, and `splats/splats_NNNN.ply` (every Gaussian of the frame as a 3DGS PLY).

pub mod cameras;
pub mod measure;
pub mod overlay;
pub mod params;
pub mod select;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::DVec3;
use pipe_mpm::{Constitutive, ModelVisitor, State};
use serde::Serialize;
use serde_json::{Value, json};

use self::cameras::{Backdrop, EditCamera, Orbit, Pose};
use self::measure::{FrameMeasure, measure, up_axis};
use self::overlay::{Arrow, FORCE_COLOR, IMPULSE_COLOR};
use self::params::{CameraSpec, Change, EditParams, MaterialEdit, param_key};
use self::select::{Acting, Targets};
use crate::io::image::Rgb8;
use crate::io::video::{self, Mp4};
use crate::physics::fit::frame_interval;
use crate::physics::material_field::read_moduli;
use crate::physics::object::{DEFAULT_CELLS, Object, ObjectSettings, Resolution, render_filter};
use crate::physics::params::{MaterialValues, Param};
use crate::physics::rollout::{Moduli, is_fluid, material_of};
use crate::pipeline::progress::Progress;
use crate::pipeline::spec::{MaterialFamily, SceneSpec};
use crate::pipeline::stage::{ParamError, StageContext, StageError, TypedStage};
use crate::scene::camera::Camera;
use crate::scene::deform::deform;
use crate::scene::frames::{FrameRow, Frames, Role};
use crate::scene::gaussians::{Gaussians, sh_coeffs};
use crate::simulate::{FrameStats, SimulateError, Stepped};
use crate::stages::material::{MaterialModel, MaterialResult};
use crate::stages::velocity::VelocityResult;

/// Why an edit did not produce its outputs.
#[derive(Debug, thiserror::Error)]
pub enum EditError {
    /// A parameter cannot be applied to this scene (an empty selection, an unknown camera, a
    /// material value missing): where (`FILE: stages.edit.NAME.field`), what and the value.
    #[error("{location}.{field}: {message}")]
    Invalid {
        /// `FILE: stages.edit.NAME`.
        location: String,
        /// The field inside the edit.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The upstream entries cannot be used.
    #[error("{0}")]
    Inputs(String),
    /// Building or simulating the object failed (a force too strong for the material, a
    /// NaN: the engine's message names the frame, substep and quantity).
    #[error("{location}: {source}")]
    Simulation {
        /// `FILE: stages.edit.NAME`.
        location: String,
        /// What failed.
        source: Box<SimulateError>,
    },
    /// An output could not be written.
    #[error("{0}")]
    Output(String),
    /// The user asked to stop.
    #[error("interrupted")]
    Interrupted,
}

/// What an edit starts from: the upstream entries' contents (or a test's scene).
#[derive(Debug, Clone)]
pub struct Scene {
    /// The canonical Gaussians; those with `simulated` false are rendered in place.
    pub gaussians: Gaussians,
    /// The pipeline's scene section (density, gravity, boundaries, material family).
    pub scene: SceneSpec,
    /// The learned material (`material`), if the pipeline has one.
    pub learned: Option<MaterialValues>,
    /// The learned material field's weights (`field.material.arrow`), when `material` kept a
    /// field: each of the edit's particles takes its E and ν at its rest position.
    pub learned_field: Option<PathBuf>,
    /// The learned initial motion, if any: linear (m/s, of the centre of mass) and angular
    /// (rad/s) velocity.
    pub velocity: Option<([f64; 3], [f64; 3])>,
    /// The learned velocity field's weights, when `velocity` kept one (added to the rigid
    /// motion at each particle's rest position with `keep_velocity`).
    pub velocity_field: Option<PathBuf>,
    /// The capture's frame interval (s; none for a single-frame capture, whose edits must
    /// give `frame_dt`) and frame count.
    pub frame_dt: Option<f64>,
    pub frames: u32,
    /// The grid unless the edit gives `cells` (the `material` stage's).
    pub grid: Resolution,
    /// The rasterizer's filter (m) in the images the Gaussians were fitted to.
    pub splat_filter: f64,
    /// The capture's cameras with their background plates.
    pub views: BTreeMap<u16, CaptureView>,
    /// The cameras rendered when the edit names none.
    pub default_views: Vec<u16>,
    /// Where the edit is written, for messages: `FILE: stages.edit.NAME`.
    pub location: String,
}

/// A camera of the capture.
#[derive(Debug, Clone)]
pub struct CaptureView {
    /// The camera.
    pub camera: Camera,
    /// Its background plate (RGB in [0, 1]), if the capture has one.
    pub plate: Option<Vec<f32>>,
}

/// `edit.json`.
#[derive(Debug, Clone, Serialize)]
pub struct EditReport {
    /// What was simulated.
    pub applied: Applied,
    /// The object every frame (frame 0 the canonical state).
    pub frames: Vec<FrameMeasure>,
    /// Per declared boundary: what it held.
    pub boundaries: Vec<BoundaryReport>,
    /// The lowest height reached (m) and its frame, next to frame 0's.
    pub height_frame0_m: f64,
    pub min_height_m: f64,
    pub min_height_frame: u32,
    /// The files written, relative to the entry.
    pub outputs: Outputs,
    /// Things the user should know.
    pub warnings: Vec<String>,
    /// Wall time (s): total, and in the simulation's substeps, rendering, and encoding.
    pub wall_time_s: f64,
    pub timing_s: BTreeMap<String, f64>,
}

/// What an edit applied.
#[derive(Debug, Clone, Serialize)]
pub struct Applied {
    /// The material simulated, and where each value came from.
    pub material: crate::simulate::spec::MaterialSpec,
    pub material_source: BTreeMap<String, String>,
    /// Initial velocity: `rest`, or the learned rigid motion.
    pub initial_velocity: Value,
    /// Gravity (m/s²).
    pub gravity: [f64; 3],
    /// The declared boundaries, in order.
    pub boundaries: Vec<String>,
    /// Output frames (frame 0 included) and their interval (s).
    pub frames: u32,
    pub frame_dt_s: f64,
    /// Grid cell (m) and cells across the object.
    pub grid_dx_m: f64,
    pub cells: f64,
    /// Simulated particles (those carrying the Gaussians and the fillers), simulated
    /// Gaussians, fillers (simulated, not rendered), Gaussians held in place, and floaters
    /// dropped.
    pub particles: usize,
    pub gaussians: usize,
    pub fillers: usize,
    pub fixed_gaussians: usize,
    pub floaters: usize,
    /// Mass simulated (kg).
    pub mass_kg: f64,
    /// The interactions, with what each acts on.
    pub interactions: Vec<Acting>,
    /// The cameras: name and definition.
    pub cameras: Vec<Value>,
    /// Simulation precision.
    pub precision: String,
    /// Things the object's setup reported (filling, grid).
    pub setup: Vec<String>,
}

/// What one declared boundary did over the edit.
#[derive(Debug, Clone, Serialize)]
pub struct BoundaryReport {
    /// The boundary.
    pub boundary: String,
    /// Most particles it acted on in one frame, and in how many frames it acted.
    pub max_contacts: usize,
    pub frames_in_contact: usize,
    /// Particles more than half a cell inside it at frame 0, and most in one frame (pushed
    /// through it; they are kept and simulated on).
    pub inside_at_start: usize,
    pub max_inside: usize,
}

/// The files an edit wrote.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Outputs {
    /// Per camera: its PNG folder, GIF and MP4 (`null` when none was written).
    pub cameras: Vec<CameraOutputs>,
    /// Why there is no MP4, when there is none.
    pub mp4_note: Option<String>,
    /// The per-frame 3DGS PLYs (a pattern), when written.
    pub splats: Option<String>,
}

/// One camera's files.
#[derive(Debug, Clone, Serialize)]
pub struct CameraOutputs {
    /// Camera name.
    pub camera: String,
    /// `renders/<camera>/NNNN.png`.
    pub frames: String,
    /// `renders/<camera>.gif`, its size and frame count.
    pub gif: String,
    pub width: u32,
    pub height: u32,
    pub gif_frames: usize,
    pub gif_ms: u32,
    /// `renders/<camera>.mp4`, if written.
    pub mp4: Option<String>,
}

/// The `edit` stage.
#[derive(Debug, Clone, Copy, Default)]
pub struct Edit;

impl TypedStage for Edit {
    type Params = EditParams;
    const KIND: &'static str = "edit";
    const VERSION: u32 = 7;
    const DESCRIPTION: &'static str = "Simulate new motion of the learned scene (forces, impulses, material, gravity and boundary changes) and render it as PNG frames, GIFs, MP4s and per-frame 3DGS PLYs";
    const UPSTREAM: &'static [&'static str] = &[
        "ingest", "init", "warmup", "velocity", "material", "evaluate",
    ];
    const NAMED_INSTANCES: bool = true;

    fn output_schemas(&self) -> Vec<(&'static str, u32)> {
        Vec::new()
    }

    fn scene_key(&self, scene: &SceneSpec) -> Value {
        let mut key = scene.physics_key();
        key["test_views"] = json!(scene.test_views);
        key
    }

    fn validate(&self, p: &EditParams) -> Result<(), ParamError> {
        params::validate(p)
    }

    fn run(&self, p: &EditParams, ctx: &mut StageContext<'_>) -> Result<(), StageError> {
        let scene = read_scene(ctx).map_err(StageError::failed)?;
        let report = run(
            &scene,
            p,
            ctx.out_dir,
            ctx.progress,
            Some(ctx.interrupt_flag()),
        )
        .map_err(|e| match e {
            EditError::Interrupted => StageError::Interrupted,
            e => StageError::failed(e),
        })?;
        ctx.progress.log(&summary(&report));
        Ok(())
    }
}

/// One line about a finished edit.
fn summary(r: &EditReport) -> String {
    let a = &r.applied;
    format!(
        "edit: {} frames, {} particles ({} fillers) carrying {} Gaussians, {:.2} kg; height \
         {:.4} m at frame 0, lowest {:.4} m (frame {}); {:.1} s",
        a.frames,
        a.particles,
        a.fillers,
        a.gaussians,
        a.mass_kg,
        r.height_frame0_m,
        r.min_height_m,
        r.min_height_frame,
        r.wall_time_s
    )
}

/// Reads what an edit needs from the upstream entries of `ctx`.
fn read_scene(ctx: &StageContext<'_>) -> Result<Scene, EditError> {
    let location = ctx.location();
    let inputs = |e: &dyn std::fmt::Display| EditError::Inputs(format!("{location}: {e}"));
    let ingest = ctx.upstream("ingest").map_err(|e| inputs(&e))?;
    let frames: Frames =
        crate::scene::table::read(&ingest.dir.join("frames.arrow")).map_err(|e| inputs(&e))?;
    let (source, entry) = match ctx.upstream("warmup") {
        Ok(w) => ("warmup", w),
        Err(_) => ("init", ctx.upstream("init").map_err(|e| inputs(&e))?),
    };
    // The colours `evaluate` refitted along the learned motion, when it kept them.
    let refitted = ctx
        .upstream("evaluate")
        .ok()
        .map(|e| e.dir.join(crate::stages::evaluate::GAUSSIANS_FILE))
        .filter(|p| p.is_file());
    let gaussians: Gaussians =
        crate::scene::table::read(&refitted.unwrap_or_else(|| entry.dir.join("gaussians.arrow")))
            .map_err(|e| inputs(&e))?;
    if gaussians.is_empty() {
        return Err(inputs(&format!("{source} produced no Gaussians")));
    }
    let material = ctx.upstream("material").ok();
    let (learned, learned_field) = match material {
        Some(m) => {
            let r: MaterialResult =
                crate::io::read_json(&m.dir.join("material.json")).map_err(|e| inputs(&e))?;
            let field =
                (r.model == MaterialModel::Field).then(|| m.dir.join("field.material.arrow"));
            (Some(learned_values(&r).map_err(|e| inputs(&e))?), field)
        }
        None => (None, None),
    };
    let mut velocity_field = None;
    let velocity = match ctx.upstream("velocity") {
        Ok(v) => {
            let r: VelocityResult =
                crate::io::read_json(&v.dir.join("velocity.json")).map_err(|e| inputs(&e))?;
            if r.model == crate::stages::velocity::VelocityModel::Field {
                velocity_field = Some(v.dir.join(crate::physics::velocity_field::WEIGHTS_FILE));
            }
            Some((r.linear_velocity, r.angular_velocity))
        }
        Err(_) => match material {
            Some(m) => {
                let r: MaterialResult =
                    crate::io::read_json(&m.dir.join("material.json")).map_err(|e| inputs(&e))?;
                Some((r.initial_velocity, r.angular_velocity))
            }
            None => None,
        },
    };
    let grid = material
        .and_then(|m| Resolution::from_params(&m.manifest.key_material.params))
        .unwrap_or(Resolution::Cells(DEFAULT_CELLS));
    let single_frame = frames.rows.iter().all(|r| r.frame == frames.rows[0].frame);
    let frame_dt = match single_frame {
        // A still capture (a PhysDreamer scene of one frame, a static multi-view set) has no
        // interval of its own; each edit states its `frame_dt`.
        true => None,
        false => Some(frame_interval(&frames.rows).map_err(|e| inputs(&e))?),
    };
    let frame_count = frames.rows.iter().map(|r| r.frame).max().unwrap_or(0);
    let train0: Vec<&FrameRow> = frames
        .rows
        .iter()
        .filter(|r| r.role == Role::Train && r.frame == 0)
        .collect();
    let splat_filter = render_filter(&train0, &gaussians);
    // Each camera's earliest row, with its plate.
    let mut views: BTreeMap<u16, CaptureView> = BTreeMap::new();
    let mut rows: Vec<&FrameRow> = frames.rows.iter().collect();
    rows.sort_by_key(|r| (r.view, r.frame));
    for r in rows {
        if views.contains_key(&r.view) {
            continue;
        }
        let plate = match &r.plate {
            Some(rel) => {
                let img =
                    crate::io::image::read_rgb8(&ingest.dir.join(rel)).map_err(|e| inputs(&e))?;
                Some(img.data.iter().map(|&v| f32::from(v) / 255.0).collect())
            }
            None => None,
        };
        views.insert(
            r.view,
            CaptureView {
                camera: Camera::from_row(r),
                plate,
            },
        );
    }
    let default_views = match ctx.scene.test_views.is_empty() {
        false => ctx.scene.test_views.clone(),
        true => views.keys().next().copied().into_iter().collect(),
    };
    Ok(Scene {
        gaussians,
        scene: ctx.scene.clone(),
        learned,
        learned_field,
        velocity,
        velocity_field,
        frame_dt,
        frames: u32::from(frame_count) + 1,
        grid,
        splat_filter,
        views,
        default_views,
        location,
    })
}

/// The change an edit makes to parameter `p`, if any.
fn change_of(edit: &MaterialEdit, p: Param) -> Option<Change> {
    edit.changes().into_iter().find(|c| c.1 == p).map(|c| c.2)
}

/// The learned field's E and ν at the edit's particles (rest positions), with the edit's
/// changes: a scale multiplies every particle's value, a value replaces the field's. `None`
/// without a learned field, or when the edit simulates another family.
fn field_moduli(
    scene: &Scene,
    edit: &MaterialEdit,
    material: &MaterialValues,
    object: &Object,
) -> Result<Option<Moduli>, String> {
    let (Some(path), Some(learned)) = (&scene.learned_field, &scene.learned) else {
        return Ok(None);
    };
    if material.family != learned.family || is_fluid(material.family) {
        return Ok(None);
    }
    let rest = object.body.state.x.iter().map(|x| x.to_array()).collect();
    let mut m = read_moduli(path, rest, learned)?;
    for (p, column) in [(Param::E, &mut m.e), (Param::Nu, &mut m.nu)] {
        match change_of(edit, p) {
            Some(Change::Value(v)) => column.fill(v),
            Some(Change::Scale { scale }) => column.iter_mut().for_each(|x| *x *= scale),
            None => {}
        }
    }
    Ok(Some(m))
}

/// `material.json` as values of its family.
fn learned_values(r: &MaterialResult) -> Result<MaterialValues, String> {
    let family: MaterialFamily = serde_json::from_value(Value::String(r.family.clone()))
        .map_err(|_| format!("material.json: unknown family `{}`", r.family))?;
    let mut values = BTreeMap::new();
    for (p, v) in [
        (Param::E, r.youngs_modulus),
        (Param::Nu, r.poisson_ratio),
        (Param::YieldStress, r.yield_stress),
        (Param::Viscosity, r.viscosity),
        (Param::BulkModulus, r.bulk_modulus),
        (Param::FrictionAngle, r.friction_angle_deg),
    ] {
        if let (Some(v), true) = (v, Param::of_family(family).contains(&p)) {
            values.insert(p, v);
        }
    }
    Ok(MaterialValues {
        family,
        density: r.density,
        values,
    })
}

/// The edit's material: the learned one (or none) with the block's changes, and where each
/// value came from.
fn resolve_material(
    scene: &Scene,
    edit: &MaterialEdit,
) -> Result<(MaterialValues, BTreeMap<String, String>), EditError> {
    let invalid = |field: String, message: String| EditError::Invalid {
        location: scene.location.clone(),
        field,
        message,
    };
    let learned = scene.learned.as_ref();
    let family = edit
        .family
        .or(learned.map(|l| l.family))
        .or(scene.scene.material)
        .ok_or_else(|| {
            invalid(
                "material.family".into(),
                "no family: the pipeline has no `material` stage and neither the scene nor \
                 the edit names one"
                    .into(),
            )
        })?;
    let mut source = BTreeMap::new();
    let base_density = learned.map_or(scene.scene.density, |l| l.density);
    let density = match edit.density {
        None => base_density,
        Some(Change::Value(v)) => v,
        Some(Change::Scale { scale }) => scale * base_density,
    };
    source.insert(
        "density".to_string(),
        describe(edit.density, learned.map_or("scene", |_| "learned")),
    );
    let family_params = Param::of_family(family);
    for (key, p, _) in edit.changes() {
        if !family_params.contains(&p) {
            return Err(invalid(
                format!("material.{key}"),
                format!(
                    "the family `{}` has no parameter `{key}` (it has {})",
                    crate::simulate::spec::family_name(family),
                    family_params
                        .iter()
                        .map(|p| param_key(*p))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ));
        }
    }
    let mut values = BTreeMap::new();
    for &p in family_params {
        let key = param_key(p);
        let change = edit.changes().into_iter().find(|c| c.1 == p).map(|c| c.2);
        let base = learned.and_then(|l| l.get(p));
        let v = match (change, base) {
            (Some(Change::Value(v)), _) => v,
            (Some(Change::Scale { scale }), Some(b)) => scale * b,
            (None, Some(b)) => b,
            // Plasticine without plastic viscosity (PAC-NeRF's).
            (None, None) if p == Param::Viscosity && family == MaterialFamily::Plasticine => 0.0,
            (Some(Change::Scale { scale }), None) => {
                return Err(invalid(
                    format!("material.{key}"),
                    format!(
                        "{{scale: {scale}}} needs a learned value to scale, and {}; give the \
                         value instead",
                        match learned {
                            None => "the pipeline has no `material` stage".to_string(),
                            Some(l) => format!(
                                "the learned `{}` material has no `{key}`",
                                crate::simulate::spec::family_name(l.family)
                            ),
                        }
                    ),
                ));
            }
            (None, None) => {
                return Err(invalid(
                    format!("material.{key}"),
                    format!(
                        "the family `{}` needs `{key}`, and {}; add it to the edit's \
                         `material:` block",
                        crate::simulate::spec::family_name(family),
                        match learned {
                            None => "the pipeline has no `material` stage".to_string(),
                            Some(l) => format!(
                                "the learned `{}` material has none",
                                crate::simulate::spec::family_name(l.family)
                            ),
                        }
                    ),
                ));
            }
        };
        values.insert(p, v);
        source.insert(key.to_string(), describe(change, "learned"));
    }
    Ok((
        MaterialValues {
            family,
            density,
            values,
        },
        source,
    ))
}

fn describe(change: Option<Change>, base: &str) -> String {
    match change {
        None => base.to_string(),
        Some(Change::Value(_)) => "edit".to_string(),
        Some(Change::Scale { scale }) => format!("{base} x {scale}"),
    }
}

/// The Gaussians that simulate and those held in place.
fn split(g: &Gaussians) -> (Gaussians, Gaussians) {
    let take = |keep: bool| {
        let idx: Vec<usize> = (0..g.len()).filter(|&i| g.simulated[i] == keep).collect();
        pick(g, &idx)
    };
    (take(true), take(false))
}

/// The Gaussians `idx` of `g`.
fn pick(g: &Gaussians, idx: &[usize]) -> Gaussians {
    let k = 3 * sh_coeffs(g.sh_degree);
    Gaussians {
        sh_degree: g.sh_degree,
        id: idx.iter().map(|&i| g.id[i]).collect(),
        position: idx.iter().map(|&i| g.position[i]).collect(),
        log_scale: idx.iter().map(|&i| g.log_scale[i]).collect(),
        rotation: idx.iter().map(|&i| g.rotation[i]).collect(),
        opacity_logit: idx.iter().map(|&i| g.opacity_logit[i]).collect(),
        sh: idx
            .iter()
            .flat_map(|&i| g.sh[i * k..(i + 1) * k].iter().copied())
            .collect(),
        simulated: idx.iter().map(|&i| g.simulated[i]).collect(),
    }
}

/// `a` followed by `b` (same SH degree).
fn concat(mut a: Gaussians, b: &Gaussians) -> Gaussians {
    a.id.extend_from_slice(&b.id);
    a.position.extend_from_slice(&b.position);
    a.log_scale.extend_from_slice(&b.log_scale);
    a.rotation.extend_from_slice(&b.rotation);
    a.opacity_logit.extend_from_slice(&b.opacity_logit);
    a.sh.extend_from_slice(&b.sh);
    a.simulated.extend_from_slice(&b.simulated);
    a
}

fn position(p: [f32; 3]) -> DVec3 {
    DVec3::new(p[0].into(), p[1].into(), p[2].into())
}

/// Runs edit `p` on `scene`, writing its outputs into `out` (created if needed).
pub fn run(
    scene: &Scene,
    p: &EditParams,
    out: &Path,
    progress: &dyn Progress,
    interrupt: Option<&AtomicBool>,
) -> Result<EditReport, EditError> {
    let started = Instant::now();
    let location = scene.location.clone();
    let invalid = |field: String, message: String| EditError::Invalid {
        location: location.clone(),
        field,
        message,
    };
    let sim_error = |e: SimulateError| EditError::Simulation {
        location: location.clone(),
        source: Box::new(e),
    };
    let output = |path: &Path, e: &dyn std::fmt::Display| {
        EditError::Output(format!("{}: {e}", path.display()))
    };
    let (material, mut material_source) = resolve_material(scene, &p.material)?;
    let mut sim_scene = scene.scene.clone();
    if let Some(g) = p.gravity {
        sim_scene.gravity = g;
    }
    if let Some(b) = &p.boundaries {
        sim_scene.boundaries = b.clone();
    }
    let frame_dt = match p.frame_dt.or(scene.frame_dt) {
        Some(dt) => dt,
        None => {
            return Err(EditError::Invalid {
                location: location.clone(),
                field: "frame_dt".into(),
                message: "the capture has a single frame, so it gives no frame interval: \
                          set `frame_dt` (s per frame, e.g. 0.0417 for 24 frames/s)"
                    .into(),
            });
        }
    };
    let frames = p.frames.unwrap_or(scene.frames).max(2);
    let grid = p.cells.map_or(scene.grid, Resolution::Cells);
    let (moving, fixed) = split(&scene.gaussians);
    if moving.is_empty() {
        return Err(EditError::Inputs(format!(
            "{location}: none of the {} Gaussians simulates (`simulated` is false for all)",
            scene.gaussians.len()
        )));
    }
    let settings = ObjectSettings {
        scene: &sim_scene,
        frame_dt,
        grid,
        material: material.spec(),
        frames,
        label: PathBuf::from(&location),
        splat_filter: scene.splat_filter,
        anchor: (p.anchor && !fixed.is_empty()).then(|| {
            std::sync::Arc::new(
                fixed
                    .position
                    .iter()
                    .map(|q| q.map(f64::from))
                    .collect::<Vec<_>>(),
            )
        }),
    };
    let mut object = Object::build(&moving, &settings).map_err(sim_error)?;
    // Cells across the object (given, or what a given cell makes of it).
    let cells = match grid {
        Resolution::Cells(cells) => cells,
        Resolution::Dx(dx) => crate::scene::neighbors::bounds(&object.body.state.x)
            .map_or(0.0, |(lo, hi)| (hi - lo).max_element() / dx),
    };
    if let Some(moduli) = field_moduli(scene, &p.material, &material, &object)
        .map_err(|e| EditError::Inputs(format!("{location}: {e}")))?
    {
        object.body.material = material_of(&object, &material, Some(&moduli)).map_err(|e| {
            EditError::Inputs(format!("{location}: the learned field's moduli: {e}"))
        })?;
        for (key, q) in [("youngs_modulus", Param::E), ("poisson_ratio", Param::Nu)] {
            if let Some(s) = material_source.get_mut(key)
                && !matches!(change_of(&p.material, q), Some(Change::Value(_)))
            {
                *s = format!("{s} (the learned field, per particle)");
            }
        }
    }
    let n_g = object.rendered();
    let fixed_x: Vec<DVec3> = fixed.position.iter().copied().map(position).collect();
    let resolved = select::resolve(
        &p.interactions,
        Targets {
            x: &object.body.state.x,
            mass: &object.body.material.mass,
            gaussians: object.carriers(),
            fixed: &fixed_x,
        },
    )
    .map_err(|e| invalid(e.field, e.message))?;
    object.body.setup.forces = resolved.forces.clone();
    let mut warnings: Vec<String> = Vec::new();
    let t_end = f64::from(frames - 1) * frame_dt;
    for (i, a) in resolved.acting.iter().enumerate() {
        if a.start_s >= t_end {
            warnings.push(format!(
                "interactions[{i}] acts from t = {} s, after the edit's last frame (t = {} s): \
                 it has no effect",
                a.start_s, t_end
            ));
        }
        if a.total.iter().all(|&c| c == 0.0) {
            warnings.push(format!("interactions[{i}] is zero: it has no effect"));
        }
    }
    // The initial velocity: at rest, or the learned rigid motion about the centre of mass.
    let com = object.centre_of_mass();
    let initial_velocity = if p.keep_velocity {
        let Some((linear, angular)) = scene.velocity else {
            return Err(invalid(
                "keep_velocity".into(),
                "true, but the pipeline has no `velocity` or `material` stage that learned one"
                    .into(),
            ));
        };
        let rigid = crate::physics::fit::RigidVelocity {
            linear,
            angular,
            centre: com.to_array(),
        };
        object.body.state.v = crate::physics::velocity_field::initial_velocities(
            &object,
            &rigid,
            scene.velocity_field.as_deref(),
        )
        .map_err(|e| EditError::Inputs(format!("{location}: {e}")))?;
        json!({
            "linear_m_s": linear,
            "angular_rad_s": angular,
            "about_m": com.to_array(),
            "field": scene.velocity_field.as_ref().map(|_| "the learned residual field, per particle"),
        })
    } else {
        object
            .body
            .state
            .v
            .iter_mut()
            .for_each(|v| *v = DVec3::ZERO);
        json!("rest")
    };

    // Cameras.
    let up = up_axis(scene.scene.gravity);
    let x0 = &object.body.state.x;
    let extent = x0
        .iter()
        .chain(&fixed_x)
        .map(|x| x.distance(com))
        .fold(0.0, f64::max);
    let specs: Vec<CameraSpec> = match &p.cameras {
        Some(c) => c.clone(),
        None => scene
            .default_views
            .iter()
            .map(|&v| CameraSpec::View(v))
            .collect(),
    };
    let mut cams: Vec<EditCamera> = Vec::new();
    let mut orbits = 0;
    for (i, spec) in specs.iter().enumerate() {
        cams.push(match spec {
            CameraSpec::View(v) => {
                let view = scene.views.get(v).ok_or_else(|| {
                    invalid(
                        format!("cameras[{i}].view"),
                        match scene.views.len() {
                            0 => format!("{v} is not a camera of the capture (it has none)"),
                            _ => format!(
                                "{v} is not a camera of the capture (it has cameras {})",
                                ranges(&scene.views.keys().copied().collect::<Vec<_>>())
                            ),
                        },
                    )
                })?;
                EditCamera {
                    name: format!("view{v}"),
                    pose: Pose::Fixed(view.camera),
                    backdrop: match &view.plate {
                        Some(pl) => Backdrop::Plate(pl.clone()),
                        None => Backdrop::Solid(p.background),
                    },
                }
            }
            CameraSpec::Orbit(o) => {
                orbits += 1;
                EditCamera {
                    name: format!("orbit{}", orbits - 1),
                    pose: Pose::Orbit(Orbit::new(o, com, extent, up, frames)),
                    backdrop: Backdrop::Solid(p.background),
                }
            }
        });
    }
    let names: Vec<&str> = cams.iter().map(|c| c.name.as_str()).collect();
    if let Some(d) = (1..names.len()).find(|&k| names[..k].contains(&names[k])) {
        return Err(invalid(
            format!("cameras[{d}]"),
            format!("`{}` is listed twice", names[d]),
        ));
    }
    let mkdir = |dir: &Path| std::fs::create_dir_all(dir).map_err(|e| output(dir, &e));
    for c in &cams {
        mkdir(&out.join("renders").join(&c.name))?;
    }
    if p.splats {
        mkdir(&out.join("splats"))?;
    }
    progress.log(&format!(
        "edit: {} ({} Gaussians held in place), {:.2} kg, dx {:.4} m, \
         {} interaction(s), {} frames of {:.4} s, {} camera(s)",
        object.particle_summary(),
        fixed.len(),
        object.mass(),
        object.body.setup.dx,
        resolved.acting.len(),
        frames,
        frame_dt,
        cams.len()
    ));

    // Arrow lengths: 0.8 of the object's bounding radius for the strongest force (impulse).
    let strongest = |kind: &str| {
        resolved
            .acting
            .iter()
            .filter(|a| a.kind == kind)
            .map(|a| DVec3::from_array(a.total).length())
            .fold(0.0, f64::max)
    };
    let (max_force, max_impulse) = (strongest("force"), strongest("impulse"));
    let family = material.family;
    let mut sink_state = Sink {
        measures: Vec::new(),
        gifs: vec![Vec::new(); cams.len()],
        error: None,
        interrupted: false,
        render_s: 0.0,
    };
    let boundaries = object.spec.boundaries.clone();
    let dx = object.body.setup.dx;
    let mass = object.body.material.mass.clone();
    let draw_arrows = |frame: u32, x: &[DVec3], cam: &Camera, img: &mut Rgb8| {
        let t = f64::from(frame) * frame_dt;
        for (a, parts) in resolved.acting.iter().zip(&resolved.particles) {
            let total = DVec3::from_array(a.total);
            let (active, strongest, color) = match a.kind {
                "force" => (
                    a.start_s <= t && a.end_s.is_none_or(|e| e > t - frame_dt),
                    max_force,
                    FORCE_COLOR,
                ),
                _ => (
                    a.start_s < t && a.start_s >= t - 3.0 * frame_dt,
                    max_impulse,
                    IMPULSE_COLOR,
                ),
            };
            if !active || strongest <= 0.0 || total.length() == 0.0 {
                continue;
            }
            let pts: Vec<DVec3> = parts.iter().map(|&q| x[q]).collect();
            let m: f64 = parts.iter().map(|&q| mass[q]).sum();
            let centre = parts.iter().map(|&q| x[q] * mass[q]).sum::<DVec3>() / m;
            let length = 0.8 * extent * (total.length() / strongest).max(0.35);
            Arrow::onto(&pts, centre, total, length, color).draw(cam, img);
        }
    };
    let relight = (p.relight && family != crate::pipeline::spec::MaterialFamily::Newtonian)
        .then(|| object.relight())
        .flatten();
    let mut sink = |frame: u32, state: &State, stats: Option<&FrameStats>| {
        let s = &mut sink_state;
        if interrupt.is_some_and(|i| i.load(Ordering::SeqCst)) {
            s.interrupted = true;
            return Ok(false);
        }
        let rendering = Instant::now();
        let mut m = measure(
            (frame, f64::from(frame) * frame_dt),
            (&state.x, &state.v, &mass),
            up,
            &boundaries,
            dx,
        );
        if let Some(st) = stats {
            m.contacts.clone_from(&st.contacts);
            m.substeps = st.substeps;
            m.substeps_reason.clone_from(&st.substeps_reason);
            m.speed_bound_m_s = st.speed_bound_m_s;
        }
        s.measures.push(m);
        let moved = match frame {
            0 => object.gaussians.clone(),
            _ => {
                let pose = object.body.input_pose(family, state);
                let (x, f) = (pose.x, pose.f);
                let mut g = deform(&object.gaussians, &x, &f);
                if let Some(r) = &relight {
                    g.sh = r.sh(&g.sh, g.sh_degree, &f);
                }
                g
            }
        };
        let all = concat(moved, &fixed);
        if p.splats {
            let path = out.join(format!("splats/splats_{frame:04}.ply"));
            if let Err(e) = crate::io::ply::write_gaussians(&path, &all) {
                s.error = Some(output(&path, &e));
                return Ok(false);
            }
        }
        for (k, cam) in cams.iter().enumerate() {
            let camera = cam.at(frame);
            match render(&all, &camera, &cam.backdrop) {
                Ok(mut img) => {
                    if p.overlay_forces {
                        draw_arrows(frame, &state.x, &camera, &mut img);
                    }
                    let path = out.join(format!("renders/{}/{frame:04}.png", cam.name));
                    if let Err(e) = crate::io::image::write_rgb8(&path, &img) {
                        s.error = Some(output(&path, &e));
                        return Ok(false);
                    }
                    s.gifs[k].push(img);
                }
                Err(e) => {
                    s.error = Some(EditError::Output(format!(
                        "{location}: rendering camera `{}` at frame {frame}: {e}",
                        cam.name
                    )));
                    return Ok(false);
                }
            }
        }
        s.render_s += rendering.elapsed().as_secs_f64();
        Ok(true)
    };
    let stepped = object.spec.material.mpm_family().visit(Simulate {
        object: &object,
        frames,
        precision: p.precision.mpm(),
        progress,
        sink: &mut sink,
    });
    if sink_state.interrupted {
        return Err(EditError::Interrupted);
    }
    if let Some(e) = sink_state.error {
        return Err(e);
    }
    let stepped = stepped.map_err(sim_error)?.ok_or(EditError::Interrupted)?;
    warnings.extend(object.body.setup.warnings.iter().cloned());
    warnings.extend(stepped.warnings.iter().cloned());

    // Videos.
    let encoding = Instant::now();
    let gif_ms = p
        .gif_ms
        .unwrap_or_else(|| ((frame_dt * 1000.0).round() as u32).max(20));
    let mut outputs = Outputs {
        splats: p.splats.then(|| "splats/splats_NNNN.ply".to_string()),
        ..Default::default()
    };
    for (cam, gif) in cams.iter().zip(&sink_state.gifs) {
        let path = out.join(format!("renders/{}.gif", cam.name));
        video::write_gif(&path, gif, gif_ms).map_err(|e| output(&path, &e))?;
        let mp4 = out.join(format!("renders/{}.mp4", cam.name));
        let written = match video::write_mp4(
            &out.join(format!("renders/{}/%04d.png", cam.name)),
            &mp4,
            1.0 / frame_dt,
        ) {
            Mp4::Written => true,
            Mp4::NoFfmpeg => {
                outputs.mp4_note = Some(
                    "ffmpeg is not on PATH: no MP4 was written (the GIFs and PNGs were)".into(),
                );
                false
            }
            Mp4::Failed(why) => {
                outputs.mp4_note = Some(format!("no MP4 was written: {why}"));
                false
            }
        };
        let first = gif.first();
        outputs.cameras.push(CameraOutputs {
            camera: cam.name.clone(),
            frames: format!("renders/{}/NNNN.png", cam.name),
            gif: format!("renders/{}.gif", cam.name),
            width: first.map_or(0, |f| f.width),
            height: first.map_or(0, |f| f.height),
            gif_frames: gif.len(),
            gif_ms,
            mp4: written.then(|| format!("renders/{}.mp4", cam.name)),
        });
    }
    if let Some(note) = &outputs.mp4_note {
        progress.notice(&format!("note: {note}"));
    }
    let encode_s = encoding.elapsed().as_secs_f64();

    let measures = sink_state.measures;
    let names = crate::simulate::setup::describe_boundaries(&boundaries, false);
    let boundary_reports: Vec<BoundaryReport> = names
        .iter()
        .enumerate()
        .map(|(b, name)| {
            let contacts = measures
                .iter()
                .map(|m| m.contacts.get(b).copied().unwrap_or(0));
            BoundaryReport {
                boundary: name.clone(),
                max_contacts: contacts.clone().max().unwrap_or(0),
                frames_in_contact: contacts.filter(|&c| c > 0).count(),
                inside_at_start: measures.first().map_or(0, |m| m.inside_boundaries[b]),
                max_inside: measures
                    .iter()
                    .map(|m| m.inside_boundaries[b])
                    .max()
                    .unwrap_or(0),
            }
        })
        .collect();
    for b in &boundary_reports {
        if b.max_inside > b.inside_at_start {
            warnings.push(format!(
                "{}: up to {} particle(s) were more than half a cell through it ({} at frame \
                 0; kept and simulated on); a weaker push or a finer grid (`cells`) holds them \
                 out",
                b.boundary, b.max_inside, b.inside_at_start
            ));
        }
    }
    for w in &warnings {
        progress.warn(w);
    }
    let (min_frame, min_height) = measures
        .iter()
        .map(|m| (m.frame, m.height_m))
        .fold((0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
    let mut timing_s = BTreeMap::new();
    timing_s.insert("substeps".to_string(), stepped.substeps_s);
    timing_s.insert("render_and_write".to_string(), sink_state.render_s);
    timing_s.insert("encode".to_string(), encode_s);
    let report = EditReport {
        applied: Applied {
            material: material.spec(),
            material_source,
            initial_velocity,
            gravity: sim_scene.gravity,
            boundaries: names,
            frames,
            frame_dt_s: frame_dt,
            grid_dx_m: dx,
            cells,
            particles: object.particles(),
            gaussians: n_g,
            fillers: object.particles() - object.carriers(),
            fixed_gaussians: fixed.len(),
            floaters: object.floaters,
            mass_kg: object.mass(),
            interactions: resolved.acting.clone(),
            cameras: specs
                .iter()
                .zip(&cams)
                .map(|(s, c)| json!({"name": c.name, "camera": s}))
                .collect(),
            precision: match p.precision.mpm() {
                pipe_mpm::Precision::F32 => "f32",
                pipe_mpm::Precision::F64 => "f64",
            }
            .into(),
            setup: vec![
                format!("fill: {}", object.body.setup.fill_source),
                format!("grid: {}", object.body.setup.domain_source),
            ],
        },
        height_frame0_m: measures.first().map_or(0.0, |m| m.height_m),
        min_height_m: min_height,
        min_height_frame: min_frame,
        frames: measures,
        boundaries: boundary_reports,
        outputs,
        warnings,
        wall_time_s: started.elapsed().as_secs_f64(),
        timing_s,
    };
    let path = out.join("edit.json");
    crate::io::write_json(&path, &report).map_err(|e| output(&path, &e))?;
    Ok(report)
}

/// What the frame sink collected.
struct Sink {
    measures: Vec<FrameMeasure>,
    /// Per camera, its frames.
    gifs: Vec<Vec<Rgb8>>,
    error: Option<EditError>,
    interrupted: bool,
    render_s: f64,
}

/// `g` rendered from `camera` over `backdrop`, as 8-bit RGB.
fn render(g: &Gaussians, camera: &Camera, backdrop: &Backdrop) -> Result<Rgb8, String> {
    let cam = crate::scene::splat::render_camera(camera);
    let opts = pipe_render::RenderOptions {
        background: [0.0; 3],
        ..Default::default()
    };
    let out = pipe_render::render(&crate::scene::splat::render_gaussians(g), &cam, &opts)
        .map_err(|e| e.to_string())?;
    let px = crate::scene::targets::composite(&out, &backdrop.pixels(camera.width, camera.height));
    Ok(Rgb8 {
        width: camera.width,
        height: camera.height,
        data: px
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect(),
    })
}

/// `0-10`, `0-3, 5, 7-9`: sorted indices as ranges.
fn ranges(v: &[u16]) -> String {
    let mut parts = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let mut j = i;
        while j + 1 < v.len() && v[j + 1] == v[j] + 1 {
            j += 1;
        }
        parts.push(if j > i {
            format!("{} to {}", v[i], v[j])
        } else {
            v[i].to_string()
        });
        i = j + 1;
    }
    parts.join(", ")
}

/// The monomorphised simulation of an edit: `pipe simulate`'s frame loop.
struct Simulate<'a, 's> {
    object: &'a Object,
    frames: u32,
    precision: pipe_mpm::Precision,
    progress: &'a dyn Progress,
    sink: &'a mut crate::simulate::FrameSink<'s>,
}

impl ModelVisitor for Simulate<'_, '_> {
    type Output = Result<Option<Stepped>, SimulateError>;

    fn visit<M: Constitutive + Clone + 'static>(self, model: M) -> Self::Output {
        let (spec, body) = (&self.object.spec, &self.object.body);
        let sim = crate::simulate::simulator(model, spec, body, self.precision)?;
        let mut state = body.state.clone();
        let mut stepper = crate::simulate::stepper(&sim, spec, body, &mut state, self.frames)?;
        crate::simulate::run_frames(
            crate::simulate::Frames {
                spec,
                body,
                sim: &sim,
                count: self.frames,
                progress: self.progress,
                deformation: true,
            },
            &mut stepper,
            &mut state,
            self.sink,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_indices_are_listed_as_ranges() {
        assert_eq!(ranges(&[0, 1, 2, 3, 5, 7, 8, 9]), "0 to 3, 5, 7 to 9");
        assert_eq!(ranges(&[4]), "4");
        assert_eq!(ranges(&[]), "");
    }
}
