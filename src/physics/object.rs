//! The simulated object of a capture: its canonical Gaussians become simulation particles,
//! as `pipe simulate` makes a 3DGS PLY one (the same [`Body`], `merge_splats`): the Gaussians
//! that share a voxel of the filling (edge `dx/2`) ride one particle
//! ([`crate::simulate::skin`]), a closed splat surface is filled with particles inside
//! (simulated, not rendered), and the
//! mass follows `scene.density` and the filled volume: the solid the splats render in the
//! images they were fitted to, so their field includes the rasterizer's low-pass filter at
//! those images' resolution ([`render_filter`]).
//!
//! Floaters (Gaussians apart from the object: clusters of grid cells not touching the main
//! one and holding under 1 % of its opacity) are dropped: a floater that stayed where it was
//! would be seen in every frame as the object moved on.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3, IVec3};

use crate::pipeline::spec::{BoundaryCondition, BoundaryItem, SceneSpec};
use crate::scene::frames::FrameRow;
use crate::scene::gaussians::{Gaussians, sh_coeffs};
use crate::simulate::fill::Splat;
use crate::simulate::spec::{MaterialSpec, SimSpec, family_name, fmt_num};
use crate::simulate::{Body, SimulateError};

/// Cells of the object's grid across its largest extent when a stage does not say.
pub const DEFAULT_CELLS: f64 = 24.0;

/// What a physics stage's object is built from, besides its Gaussians.
#[derive(Debug, Clone)]
pub struct ObjectSettings<'a> {
    /// The pipeline's scene section (density, gravity, boundaries).
    pub scene: &'a SceneSpec,
    /// Time between frames (s).
    pub frame_dt: f64,
    /// How fine the grid is.
    pub grid: Resolution,
    /// The material to build the body with (its masses and volumes do not depend on it).
    pub material: MaterialSpec,
    /// Frames the body is simulated for (only the summary's time estimates use it).
    pub frames: u32,
    /// Names the source in messages (e.g. the pipeline file and stage).
    pub label: PathBuf,
    /// The rasterizer's low-pass filter (m) in the images the Gaussians were fitted to
    /// ([`render_filter`]); 0 for none.
    pub splat_filter: f64,
    /// Centres (m) of Gaussians that do not simulate, to anchor the body to where it meets
    /// them ([`crate::simulate::spec::BoundarySpec::Anchor`]); `None`: no anchor.
    pub anchor: Option<std::sync::Arc<Vec<[f64; 3]>>>,
}

/// How fine a physics stage's grid is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Resolution {
    /// Cells across the filled solid's largest extent.
    Cells(f64),
    /// Cell edge (m), whatever the object's size.
    Dx(f64),
}

impl Resolution {
    /// A stage's `cells` and `dx` (m): `dx` wins when set.
    pub fn of(cells: f64, dx: Option<f64>) -> Self {
        dx.map_or(Self::Cells(cells), Self::Dx)
    }

    /// Checks a stage's `cells` (in [4, [`MAX_CELLS`]]) and `dx` (a length > 0 m when set):
    /// the field at fault and why.
    pub fn check(cells: f64, dx: Option<f64>) -> Result<(), (&'static str, String)> {
        if !(cells.is_finite() && (4.0..=MAX_CELLS).contains(&cells)) {
            return Err((
                "cells",
                format!("must be in [4, {MAX_CELLS}], found {cells}"),
            ));
        }
        match dx {
            Some(dx) if !(dx.is_finite() && dx > 0.0) => {
                Err(("dx", format!("must be a cell edge > 0 m, found {dx}")))
            }
            _ => Ok(()),
        }
    }

    /// From a physics stage's resolved parameters (`cells`, and `dx` when set).
    pub fn from_params(params: &serde_json::Value) -> Option<Self> {
        let cells = params["cells"].as_f64()?;
        Some(Self::of(cells, params["dx"].as_f64()))
    }
}

/// Most cells across the object, given as `cells` or made by a `dx`.
pub const MAX_CELLS: f64 = 512.0;

/// The simulated object.
#[derive(Debug, Clone)]
pub struct Object {
    /// The simulated Gaussians, canonical: Gaussian `g` rides particle `body.skin.carrier()[g]`.
    pub gaussians: Gaussians,
    /// Gaussians dropped as floaters.
    pub floaters: usize,
    /// The simulation file the body was built from (at the material it was built with).
    pub spec: SimSpec,
    /// Particles (those that carry the Gaussians, then the fillers), their settings and
    /// material.
    pub body: Body,
}

impl Object {
    /// Particles (carriers of Gaussians and fillers).
    pub fn particles(&self) -> usize {
        self.body.state.len()
    }

    /// Gaussians rendered.
    pub fn rendered(&self) -> usize {
        self.gaussians.len()
    }

    /// Particles that carry Gaussians (the first ones).
    pub fn carriers(&self) -> usize {
        self.body.n_input
    }

    /// `N particles: C carrying G Gaussians, F fillers`, for the stages' logs.
    pub fn particle_summary(&self) -> String {
        format!(
            "{} particles: {} carrying {} Gaussians, {} fillers",
            self.particles(),
            self.carriers(),
            self.rendered(),
            self.particles() - self.carriers()
        )
    }

    /// How the Gaussians ride the particles.
    pub fn skin(&self) -> &crate::simulate::skin::Skin {
        &self.body.skin
    }

    /// Each Gaussian's deformation gradient: its carrier's `F` in `f` (one per particle).
    pub fn gaussian_f<'a>(&self, f: &'a [DMat3]) -> std::borrow::Cow<'a, [DMat3]> {
        self.body.skin.gather(f)
    }

    /// The re-lighting of the Gaussians when the body deforms ([`crate::scene::shading`]):
    /// normals from the particles at rest, the irradiance fitted to the canonical colours;
    /// `None` when too few Gaussians have a normal.
    pub fn relight(&self) -> Option<crate::scene::shading::Relight> {
        crate::scene::shading::Relight::of(
            &self.body.state.x,
            &self.body.material.volume,
            &self.gaussians,
            self.body.setup.dx,
        )
    }

    /// Total mass (kg).
    pub fn mass(&self) -> f64 {
        self.body.material.mass.iter().sum()
    }

    /// The mass-weighted centre (m) of the initial state.
    pub fn centre_of_mass(&self) -> DVec3 {
        self.body.centre_of_mass()
    }

    /// The object of `gaussians` (canonical, e.g. the `warmup` fit).
    ///
    /// With [`Resolution::Dx`] the grid has that cell (refused when it puts more than
    /// [`MAX_CELLS`] across the object). With [`Resolution::Cells`] it has that many cells
    /// across the filled solid's largest extent. The Gaussians'
    /// own box gives the first estimate; when faint splats around the body (which ride it and
    /// weigh nothing) make that box larger than the solid by more than a cell, the body is
    /// built again on the solid's box: from four cameras a loose visual hull left faint splats
    /// over a metre for a 0.3 m blob, and its grid was three times too coarse.
    pub fn build(gaussians: &Gaussians, s: &ObjectSettings<'_>) -> Result<Self, SimulateError> {
        let x: Vec<DVec3> = gaussians
            .position
            .iter()
            .map(|p| DVec3::new(p[0].into(), p[1].into(), p[2].into()))
            .collect();
        let (lo, hi) =
            crate::scene::neighbors::bounds(&x).ok_or_else(|| SimulateError::NoParticles {
                path: s.label.clone(),
            })?;
        let extent = (hi - lo).max_element().max(1e-6);
        let cells = match s.grid {
            Resolution::Cells(cells) => cells,
            Resolution::Dx(dx) => {
                let across = extent / dx;
                if !(dx.is_finite() && dx > 0.0 && across <= MAX_CELLS) {
                    return Err(SimulateError::Spacing {
                        path: PathBuf::from(format!("{}.dx", s.label.display())),
                        message: format!(
                            "a cell of {dx} m puts {across:.0} cells across the object's {extent:.3} m; at most {MAX_CELLS} are allowed (set a larger `dx` or `cells`)"
                        ),
                    });
                }
                return Self::build_on(gaussians, &x, s, dx);
            }
        };
        let first = Self::build_on(gaussians, &x, s, extent / cells)?;
        let solid = crate::scene::neighbors::bounds(&first.body.state.x)
            .map_or(extent, |(lo, hi)| (hi - lo).max_element().max(1e-6));
        if extent - solid > first.body.setup.dx {
            Self::build_on(gaussians, &x, s, solid / cells)
        } else {
            Ok(first)
        }
    }

    /// The body of `gaussians` (centres `x`, m) on a grid of cell `dx` (m).
    fn build_on(
        gaussians: &Gaussians,
        x: &[DVec3],
        s: &ObjectSettings<'_>,
        dx: f64,
    ) -> Result<Self, SimulateError> {
        let keep = main_body(gaussians, dx);
        let kept = select(gaussians, &keep);
        let floaters = gaussians.len() - kept.len();
        let x0: Vec<DVec3> = keep.iter().map(|&i| x[i]).collect();
        let splats: Vec<Splat> = keep
            .iter()
            .filter_map(|&i| {
                Splat::from_3dgs(
                    x[i],
                    gaussians.log_scale[i].map(f64::from),
                    gaussians.rotation[i].map(f64::from),
                    f64::from(gaussians.opacity_logit[i]),
                )
                .map(|sp| sp.filtered(s.splat_filter))
            })
            .collect();
        let text = sim_yaml(
            &s.material,
            &crate::physics::fit::RigidVelocity::default(),
            s.scene,
            s.frame_dt,
            dx,
            Some(true),
            s.splat_filter,
        );
        let mut spec = SimSpec::parse(&s.label, &text)?;
        if let Some(still) = &s.anchor {
            spec.boundaries
                .push(crate::simulate::spec::BoundarySpec::Anchor {
                    still: still.clone(),
                });
        }
        let body = Body::new(&spec, &s.label, x0, &splats, s.frames)?;
        Ok(Self {
            gaussians: kept,
            floaters,
            spec,
            body,
        })
    }
}

/// The low-pass filter (m) the rasterizer applied to `gaussians` in the images of the cameras
/// `views`: 3DGS adds `eps2d` = 0.3 px² to every projected covariance, which is a 3D filter
/// of `s = √eps2d · depth / f` about a Gaussian at `depth` (m) from a camera of focal length
/// `f` (px); the median over the views, at the Gaussians' centroid. 0 without views or
/// Gaussians.
pub fn render_filter(views: &[&FrameRow], gaussians: &Gaussians) -> f64 {
    if gaussians.is_empty() {
        return 0.0;
    }
    let centroid = gaussians
        .position
        .iter()
        .map(|p| DVec3::new(p[0].into(), p[1].into(), p[2].into()))
        .sum::<DVec3>()
        / gaussians.len() as f64;
    let eps2d = pipe_render::RenderOptions::<f64>::default().eps2d;
    let mut s: Vec<f64> = views
        .iter()
        .map(|r| {
            let m = &r.world_from_camera;
            let eye = DVec3::new(m[3], m[7], m[11]);
            let axis = DVec3::new(m[2], m[6], m[10]);
            let depth = (centroid - eye).dot(axis.normalize_or_zero());
            eps2d.sqrt() * depth / (0.5 * (r.fx + r.fy))
        })
        .filter(|s| s.is_finite() && *s > 0.0)
        .collect();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(0.0)
}

/// The Gaussians of the object's main body: every Gaussian in a cluster of 26-connected grid
/// cells of edge `dx` that holds the most opacity, or at least 1 % of it.
fn main_body(g: &Gaussians, dx: f64) -> Vec<usize> {
    let cell = |p: [f32; 3]| {
        (DVec3::new(p[0].into(), p[1].into(), p[2].into()) / dx)
            .floor()
            .as_ivec3()
    };
    let mut cells: BTreeMap<(i32, i32, i32), f64> = BTreeMap::new();
    for (p, l) in g.position.iter().zip(&g.opacity_logit) {
        let c = cell(*p);
        *cells.entry((c.x, c.y, c.z)).or_default() += 1.0 / (1.0 + (-f64::from(*l)).exp());
    }
    // Connected components by flood fill, in key order (deterministic).
    let mut label: BTreeMap<(i32, i32, i32), usize> = BTreeMap::new();
    let mut weight: Vec<f64> = Vec::new();
    for &start in cells.keys() {
        if label.contains_key(&start) {
            continue;
        }
        let id = weight.len();
        weight.push(0.0);
        let mut stack = vec![start];
        label.insert(start, id);
        while let Some(c) = stack.pop() {
            weight[id] += cells[&c];
            for d in 0..27 {
                let o = IVec3::new(d / 9 - 1, (d / 3) % 3 - 1, d % 3 - 1);
                let n = (c.0 + o.x, c.1 + o.y, c.2 + o.z);
                if cells.contains_key(&n) && !label.contains_key(&n) {
                    label.insert(n, id);
                    stack.push(n);
                }
            }
        }
    }
    let top = weight.iter().copied().fold(0.0, f64::max);
    (0..g.len())
        .filter(|&i| {
            let c = cell(g.position[i]);
            weight[label[&(c.x, c.y, c.z)]] >= 0.01 * top
        })
        .collect()
}

/// The Gaussians `keep` of `g`, in that order.
fn select(g: &Gaussians, keep: &[usize]) -> Gaussians {
    let k = 3 * sh_coeffs(g.sh_degree);
    Gaussians {
        sh_degree: g.sh_degree,
        id: keep.iter().map(|&i| g.id[i]).collect(),
        position: keep.iter().map(|&i| g.position[i]).collect(),
        log_scale: keep.iter().map(|&i| g.log_scale[i]).collect(),
        rotation: keep.iter().map(|&i| g.rotation[i]).collect(),
        opacity_logit: keep.iter().map(|&i| g.opacity_logit[i]).collect(),
        sh: keep
            .iter()
            .flat_map(|&i| g.sh[i * k..(i + 1) * k].iter().copied())
            .collect(),
        simulated: vec![true; keep.len()],
    }
}

/// A simulation file (`pipe simulate --material`) for the object of `scene` with `material`,
/// the initial rigid `motion` (`v + ω × (x − c)`; the angular velocity and its centre are
/// written only when `ω ≠ 0`), `frame_dt` (s), cell `grid_dx` (m) and, when given,
/// `fill_interior`.
pub fn sim_yaml(
    material: &MaterialSpec,
    motion: &crate::physics::fit::RigidVelocity,
    scene: &SceneSpec,
    frame_dt: f64,
    grid_dx: f64,
    fill_interior: Option<bool>,
    splat_filter: f64,
) -> String {
    let num = |v: f64| fmt_num(v);
    let vec3 = |v: [f64; 3]| format!("[{}, {}, {}]", num(v[0]), num(v[1]), num(v[2]));
    let mut t = String::new();
    let _ = writeln!(t, "material:");
    let _ = writeln!(t, "  family: {}", family_name(material.family));
    for (key, value) in [
        ("youngs_modulus", material.youngs_modulus),
        ("poisson_ratio", material.poisson_ratio),
        ("yield_stress", material.yield_stress),
        ("viscosity", material.viscosity),
        ("bulk_modulus", material.bulk_modulus),
        ("friction_angle_deg", material.friction_angle_deg),
    ] {
        if let Some(v) = value {
            let _ = writeln!(t, "  {key}: {}", num(v));
        }
    }
    let _ = writeln!(t, "  density: {}", num(material.density));
    let _ = writeln!(t, "initial_velocity: {}", vec3(motion.linear));
    if motion.angular != [0.0; 3] {
        let _ = writeln!(t, "angular_velocity: {}", vec3(motion.angular));
        let _ = writeln!(t, "spin_centre: {}", vec3(motion.centre));
    }
    let _ = writeln!(t, "gravity: {}", vec3(scene.gravity));
    let _ = writeln!(t, "frame_dt: {}", num(frame_dt));
    let _ = writeln!(t, "grid_dx: {}", num(grid_dx));
    if let Some(n) = scene.prefer_substeps {
        let _ = writeln!(t, "prefer_substeps: {n}");
    }
    if let Some(f) = fill_interior {
        let _ = writeln!(t, "fill_interior: {f}");
    }
    // The splats' solid as the stages measure it (the rasterizer's filter in the warm-up's
    // images), and the splats that share a voxel of the filling riding one particle
    // (`simulate::skin`): `pipe simulate` then builds the stages' particles.
    let _ = writeln!(t, "splat_filter: {}", num(splat_filter));
    let _ = writeln!(t, "merge_splats: true");
    if scene.boundaries.is_empty() {
        let _ = writeln!(t, "boundaries: []");
    } else {
        let _ = writeln!(t, "boundaries:");
    }
    let cond = |c: BoundaryCondition| match c {
        BoundaryCondition::Sticky => "sticky",
        BoundaryCondition::Slip => "slip",
        BoundaryCondition::Separate => "separate",
    };
    for b in &scene.boundaries {
        let _ = match b {
            BoundaryItem::Ground { y, condition } => writeln!(
                t,
                "  - {{kind: ground, y: {}, condition: {}}}",
                num(*y),
                cond(*condition)
            ),
            BoundaryItem::HalfSpace {
                point,
                normal,
                condition,
            } => writeln!(
                t,
                "  - {{kind: half_space, point: {}, normal: {}, condition: {}}}",
                vec3(*point),
                vec3(*normal),
                cond(*condition)
            ),
            BoundaryItem::Box {
                min,
                max,
                condition,
            } => writeln!(
                t,
                "  - {{kind: box, min: {}, max: {}, condition: {}}}",
                vec3(*min),
                vec3(*max),
                cond(*condition)
            ),
        };
    }
    t
}

/// The label a stage's object gets in messages: `FILE (stage S)`.
pub fn label(pipeline_file: &Path, stage: &str) -> PathBuf {
    PathBuf::from(format!("{} (stage {stage})", pipeline_file.display()))
}
