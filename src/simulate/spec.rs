//! The simulation file (`SIM.yaml`): YAML → a validated [`SimSpec`].
//!
//! ```yaml
//! material:
//!   family: elastic            # elastic | elastic_fcr | plasticine | non_newtonian | newtonian | sand
//!   youngs_modulus: 3.0e5      # Pa
//!   poisson_ratio: 0.3
//!   density: 1000              # kg/m^3
//! initial_velocity: [0.5, 0.0, -0.3]   # m/s, default 0
//! angular_velocity: [0.0, 6.0, 0.0]    # rad/s about the centre of mass, default 0
//! particle_volume: 1.0e-6              # m^3; default spacing^3
//! gravity: [0, -9.8, 0]                # m/s^2, default (0, -9.8, 0)
//! frame_dt: 0.041666666666666664       # s, required
//! grid_dx: 0.02                        # m; default 2 x spacing
//! boundaries:
//!   - {kind: ground, y: 0.0, condition: sticky}    # sticky | slip | separate
//! ```
//!
//! Material parameters per family (all in SI units; `density` is always required):
//!
//! | family | parameters |
//! |---|---|
//! | `elastic`, `elastic_fcr` | `youngs_modulus` (Pa), `poisson_ratio` |
//! | `plasticine` | `youngs_modulus`, `poisson_ratio`, `yield_stress` (Pa), `viscosity` (Pa·s, optional, default 0) |
//! | `non_newtonian` | `youngs_modulus`, `poisson_ratio`, `yield_stress` (Pa), `viscosity` (Pa·s) |
//! | `newtonian` | `viscosity` (μ, Pa·s), `bulk_modulus` (κ, Pa) |
//! | `sand` | `youngs_modulus`, `poisson_ratio`, `friction_angle_deg` (degrees) |
//!
//! A body that spins starts with the rigid motion `v_p = initial_velocity + ω × (x_p − c)`
//! (`ω` = `angular_velocity`, `c` = `spin_centre`, m, default the centre of mass of every
//! simulated particle, fillers included): `initial_velocity` is then the centre's velocity.
//!
//! Other keys: `domain: {min: [..], max: [..]}` (m; default: see [`super::setup`]),
//! `substeps` (a fixed count per frame; refused above the stability limit unless
//! `allow_unstable: true`), `prefer_substeps` (that many per frame whenever a fixed count
//! may take them, i.e. within the CFL number 0.5 and the viscous limit, else the automatic
//! count: the step of the simulator that made a synthetic capture, since MPM's results depend
//! on the step; not with `substeps`), `fill_interior` (`true`/`false`; default: fill when the cloud is
//! surface-like, e.g. 3DGS splats, see [`super::fill`]), `splat_filter` (m, ≥ 0; default 0:
//! the rasterizer's low-pass filter in the images a 3DGS PLY was fitted to, `√0.3 · depth /
//! focal`, added to every splat when the filling measures the surface they render),
//! `merge_splats` (`true`/`false`, default `false`: the splats of a filled 3DGS cloud that share
//! a voxel of the filling ride one particle, see [`super::skin`]; forces then act per
//! particle), and
//! `boundaries:` items `{kind: ground, y, condition}`, `{kind: half_space, point, normal,
//! condition}` (normal points into the free side), `{kind: box, min, max, condition}`
//! (`condition` defaults to `sticky`, ground `y` to 0), and `forces:` items
//! `{kind: force, particles, force: [N per particle], start: s, end: s}` (end optional) and
//! `{kind: impulse, particles, impulse: [N·s per particle], time: s}`, where `particles` is
//! `all`, a list of indices into the input PLY, or a box `{min: [..], max: [..]}` selecting the
//! particles of the initial state inside it (always the input's particles: the fillers of a
//! filled surface follow through the material).
//!
//! Every error names the file, the key, its line and column and the offending value; unknown
//! keys get the nearest valid one.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::SimulateError;
use crate::pipeline::spec::{MaterialFamily, SpecError, suggest};
use crate::pipeline::yaml::{self, Position, Positions};

/// How a boundary treats grid velocities.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Condition {
    /// Velocity set to zero.
    #[default]
    Sticky,
    /// Normal component removed, tangential kept.
    Slip,
    /// Normal component removed only when moving into the obstacle.
    Separate,
}

impl Condition {
    /// The simulator's boundary kind.
    pub fn kind(self) -> pipe_mpm::BoundaryKind {
        match self {
            Condition::Sticky => pipe_mpm::BoundaryKind::Sticky,
            Condition::Slip => pipe_mpm::BoundaryKind::Slip,
            Condition::Separate => pipe_mpm::BoundaryKind::Separate,
        }
    }
}

/// An axis-aligned box (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// Lower corner (m).
    pub min: [f64; 3],
    /// Upper corner (m).
    pub max: [f64; 3],
}

/// One `boundaries:` item.
#[derive(Debug, Clone, PartialEq)]
pub enum BoundarySpec {
    /// The plane `y = y` (m), free side above.
    Ground {
        /// Height (m).
        y: f64,
        /// Treatment.
        condition: Condition,
    },
    /// The plane through `point` (m) with unit `normal` pointing into the free side.
    HalfSpace {
        /// A point on the plane (m).
        point: [f64; 3],
        /// Unit normal (normalised from the file's).
        normal: [f64; 3],
        /// Treatment.
        condition: Condition,
    },
    /// A solid box obstacle (m).
    Box {
        /// The box.
        aabb: BoxSpec,
        /// Treatment.
        condition: Condition,
    },
    /// An anchor (not written in simulation files: the `edit` stage adds it): the grid nodes
    /// within a cell of the still points (m) that lie within two cells of a simulated particle
    /// are held still, so a moving part stays joined to what does not simulate.
    Anchor {
        /// Centres of the Gaussians that do not simulate.
        still: std::sync::Arc<Vec<[f64; 3]>>,
    },
}

/// Which particles a force acts on.
#[derive(Debug, Clone, PartialEq)]
pub enum ParticleSet {
    /// Every particle.
    All,
    /// Indices into the input PLY's vertices.
    Indices(Vec<u64>),
    /// Particles of the initial state inside the (closed) box.
    Box(BoxSpec),
}

/// One `forces:` item.
#[derive(Debug, Clone, PartialEq)]
pub enum ForceSpec {
    /// A constant force (N per particle) while `start ≤ t < end` (s).
    Force {
        /// Target particles.
        particles: ParticleSet,
        /// Force per particle (N).
        force: [f64; 3],
        /// Window start (s).
        start: f64,
        /// Window end (s); `None` = until the end of the simulation.
        end: Option<f64>,
    },
    /// An impulse (N·s per particle) at time `time` (s).
    Impulse {
        /// Target particles.
        particles: ParticleSet,
        /// Impulse per particle (N·s).
        impulse: [f64; 3],
        /// Time (s).
        time: f64,
    },
}

/// The `material:` section, checked against its family.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaterialSpec {
    /// Family.
    pub family: MaterialFamily,
    /// Density ρ (kg/m³).
    pub density: f64,
    /// Young's modulus E (Pa), elastic-solid families.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub youngs_modulus: Option<f64>,
    /// Poisson ratio ν, elastic-solid families.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub poisson_ratio: Option<f64>,
    /// Yield stress τ_Y (Pa): plasticine, non_newtonian.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub yield_stress: Option<f64>,
    /// Viscosity (Pa·s): plasticine / non_newtonian η, newtonian μ.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub viscosity: Option<f64>,
    /// Bulk modulus κ (Pa): newtonian.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bulk_modulus: Option<f64>,
    /// Friction angle φ (degrees): sand.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub friction_angle_deg: Option<f64>,
}

impl MaterialSpec {
    /// The family's name as written in the file.
    pub fn family_name(&self) -> &'static str {
        family_name(self.family)
    }

    /// The simulator family with its global parameters.
    pub fn mpm_family(&self) -> pipe_mpm::Family {
        use pipe_mpm::Family;
        let name = match self.family {
            MaterialFamily::Elastic => "elastic",
            MaterialFamily::ElasticFcr => "fixed_corotated",
            MaterialFamily::Plasticine => "plasticine",
            MaterialFamily::NonNewtonian => "non_newtonian",
            MaterialFamily::Newtonian => "newtonian",
            MaterialFamily::Sand => "sand",
        };
        match Family::from_name(name).expect("every file family has a simulator model") {
            Family::VonMises { .. } => Family::VonMises {
                yield_stress: self.yield_stress.unwrap_or(0.0),
                eta: self.viscosity.unwrap_or(0.0),
            },
            Family::DruckerPrager { .. } => Family::DruckerPrager {
                friction_angle_deg: self.friction_angle_deg.unwrap_or(30.0),
            },
            other => other,
        }
    }

    /// Uniform per-particle material for `n` particles of volume `volume` (m³).
    pub fn material(
        &self,
        n: usize,
        volume: f64,
    ) -> Result<pipe_mpm::Material, pipe_mpm::MpmError> {
        match self.family {
            MaterialFamily::Newtonian => pipe_mpm::Material::fluid(
                n,
                volume,
                self.density,
                self.viscosity.unwrap_or(0.0),
                self.bulk_modulus.unwrap_or(0.0),
            ),
            _ => pipe_mpm::Material::from_e_nu(
                n,
                volume,
                self.density,
                self.youngs_modulus.unwrap_or(0.0),
                self.poisson_ratio.unwrap_or(0.0),
            ),
        }
    }
}

/// A loaded, validated simulation file.
#[derive(Debug, Clone)]
pub struct SimSpec {
    /// The file it came from.
    pub file: PathBuf,
    /// `material:`.
    pub material: MaterialSpec,
    /// Initial velocity (m/s): of every particle, or of `spin_centre` when the body spins.
    pub initial_velocity: [f64; 3],
    /// Initial angular velocity (rad/s) about `spin_centre`.
    pub angular_velocity: [f64; 3],
    /// The point the body spins about (m); `None` = the centre of mass of the simulated
    /// particles.
    pub spin_centre: Option<[f64; 3]>,
    /// Volume of one particle (m³); `None` = spacing³.
    pub particle_volume: Option<f64>,
    /// Gravity (m/s²).
    pub gravity: [f64; 3],
    /// Time between output frames (s).
    pub frame_dt: f64,
    /// Grid cell size (m); `None` = 2 × spacing.
    pub grid_dx: Option<f64>,
    /// Box the particles are held in (m); `None` = automatic.
    pub domain: Option<BoxSpec>,
    /// Colliders, in file order (the domain walls come on top).
    pub boundaries: Vec<BoundarySpec>,
    /// A user-fixed substep count per frame.
    pub substeps: Option<u32>,
    /// The substeps per frame to take whenever a fixed count may (else the automatic count).
    pub prefer_substeps: Option<u32>,
    /// Accept a fixed `substeps` above the stability limit (with a warning).
    pub allow_unstable: bool,
    /// Fill a closed surface with particles; `None` = when the cloud is surface-like.
    pub fill_interior: Option<bool>,
    /// The rasterizer's filter (m) in the images a 3DGS input was fitted to (0: none).
    pub splat_filter: f64,
    /// Splats that share a voxel of the filling ride one particle ([`super::skin`]).
    pub merge_splats: bool,
    /// External forces and impulses.
    pub forces: Vec<ForceSpec>,
    positions: Positions,
}

/// The largest `prefer_substeps` accepted.
pub const MAX_PREFER_SUBSTEPS: u64 = 100_000;

impl SimSpec {
    /// Validates simulation-file text; `path` names it in messages.
    pub fn parse(path: &Path, text: &str) -> Result<Self, SimulateError> {
        let file = path.display().to_string();
        let (root, positions) = yaml::parse(text).map_err(|e| {
            SimulateError::Spec(SpecError {
                file: file.clone(),
                position: e.position,
                message: e.message,
                hint: None,
            })
        })?;
        let ctx = Ctx {
            file,
            positions: &positions,
        };
        if !root.is_object() {
            return Err(ctx.err(
                Some(Position { line: 1, col: 1 }),
                "a simulation file is a mapping with `material`, `frame_dt` and optional settings"
                    .into(),
                None,
            ));
        }
        let raw: RawSpec = ctx.de(&root, "")?;
        let material = ctx.material(&raw.material)?;
        let frame_dt = ctx.positive("frame_dt", raw.frame_dt, "s")?;
        let grid_dx = raw
            .grid_dx
            .map(|v| ctx.positive("grid_dx", v, "m"))
            .transpose()?;
        let particle_volume = raw
            .particle_volume
            .map(|v| ctx.positive("particle_volume", v, "m^3"))
            .transpose()?;
        let splat_filter = match raw.splat_filter {
            Some(v) if !(v.is_finite() && v >= 0.0) => {
                return Err(ctx.bad("splat_filter", &fmt_num(v), "must be >= 0 (m)"));
            }
            v => v.unwrap_or(0.0),
        };
        let substeps = match raw.substeps {
            None => None,
            Some(n) if (1..=10_000_000).contains(&n) => Some(n as u32),
            Some(n) => {
                return Err(ctx.bad(
                    "substeps",
                    &n.to_string(),
                    "must be an integer from 1 to 10000000 (or left out to use the stability limit)",
                ));
            }
        };
        let prefer_substeps = match raw.prefer_substeps {
            None => None,
            Some(n) if substeps.is_some() => {
                return Err(ctx.bad(
                    "prefer_substeps",
                    &n.to_string(),
                    "cannot be given with `substeps` (a fixed count); keep one of them",
                ));
            }
            Some(n) if (1..=MAX_PREFER_SUBSTEPS).contains(&n) => Some(n as u32),
            Some(n) => {
                return Err(ctx.bad(
                    "prefer_substeps",
                    &n.to_string(),
                    &format!("must be an integer from 1 to {MAX_PREFER_SUBSTEPS}"),
                ));
            }
        };
        for (key, v) in [
            ("initial_velocity", Some(raw.initial_velocity)),
            ("angular_velocity", Some(raw.angular_velocity)),
            ("spin_centre", raw.spin_centre),
            ("gravity", Some(raw.gravity)),
        ] {
            if let Some(v) = v.filter(|v| v.iter().any(|x| !x.is_finite())) {
                return Err(ctx.bad(key, &format!("{v:?}"), "must be three finite numbers"));
            }
        }
        let domain = raw.domain.map(|b| ctx.check_box("domain", b)).transpose()?;
        let boundaries = raw
            .boundaries
            .iter()
            .enumerate()
            .map(|(i, v)| ctx.boundary(i, v))
            .collect::<Result<Vec<_>, _>>()?;
        let forces = raw
            .forces
            .iter()
            .enumerate()
            .map(|(i, v)| ctx.force(i, v))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            file: path.to_path_buf(),
            material,
            initial_velocity: raw.initial_velocity,
            angular_velocity: raw.angular_velocity,
            spin_centre: raw.spin_centre,
            particle_volume,
            gravity: raw.gravity,
            frame_dt,
            grid_dx,
            domain,
            boundaries,
            substeps,
            prefer_substeps,
            allow_unstable: raw.allow_unstable,
            fill_interior: raw.fill_interior,
            splat_filter,
            merge_splats: raw.merge_splats,
            forces,
            positions,
        })
    }

    /// Line and column of the value at a dotted path (`forces[0].particles[2]`), for messages.
    pub fn position(&self, path: &str) -> Option<Position> {
        self.positions.value(path)
    }

    /// An error located at the value of `path` in this file.
    pub(crate) fn error_at(
        &self,
        path: &str,
        message: String,
        hint: Option<String>,
    ) -> SimulateError {
        SimulateError::Spec(SpecError {
            file: self.file.display().to_string(),
            position: self.position(path),
            message,
            hint,
        })
    }
}

/// Reads and validates a simulation file.
pub fn load_spec(path: &Path) -> Result<SimSpec, SimulateError> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        SimulateError::Spec(SpecError {
            file: path.display().to_string(),
            position: None,
            message: format!("cannot read the simulation file: {e}"),
            hint: None,
        })
    })?;
    SimSpec::parse(path, &text)
}

/// Lower-case family name as written in the file.
pub fn family_name(f: MaterialFamily) -> &'static str {
    match f {
        MaterialFamily::Elastic => "elastic",
        MaterialFamily::ElasticFcr => "elastic_fcr",
        MaterialFamily::Plasticine => "plasticine",
        MaterialFamily::NonNewtonian => "non_newtonian",
        MaterialFamily::Newtonian => "newtonian",
        MaterialFamily::Sand => "sand",
    }
}

const FAMILIES: [MaterialFamily; 6] = [
    MaterialFamily::Elastic,
    MaterialFamily::ElasticFcr,
    MaterialFamily::Plasticine,
    MaterialFamily::NonNewtonian,
    MaterialFamily::Newtonian,
    MaterialFamily::Sand,
];

/// `(required, optional)` parameters of a family besides `density`.
fn family_params(f: MaterialFamily) -> (&'static [&'static str], &'static [&'static str]) {
    match f {
        MaterialFamily::Elastic | MaterialFamily::ElasticFcr => {
            (&["youngs_modulus", "poisson_ratio"], &[])
        }
        MaterialFamily::Plasticine => (
            &["youngs_modulus", "poisson_ratio", "yield_stress"],
            &["viscosity"],
        ),
        MaterialFamily::NonNewtonian => (
            &[
                "youngs_modulus",
                "poisson_ratio",
                "yield_stress",
                "viscosity",
            ],
            &[],
        ),
        MaterialFamily::Newtonian => (&["viscosity", "bulk_modulus"], &[]),
        MaterialFamily::Sand => (
            &["youngs_modulus", "poisson_ratio", "friction_angle_deg"],
            &[],
        ),
    }
}

/// What a material parameter is, for messages.
fn describe(param: &str) -> &'static str {
    match param {
        "youngs_modulus" => "Young's modulus E in Pa",
        "poisson_ratio" => "Poisson ratio ν",
        "yield_stress" => "yield stress τ_Y in Pa",
        "viscosity" => "viscosity in Pa·s",
        "bulk_modulus" => "bulk modulus κ in Pa",
        "friction_angle_deg" => "friction angle φ in degrees",
        _ => "a material parameter",
    }
}

fn default_gravity() -> [f64; 3] {
    [0.0, -9.8, 0.0]
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSpec {
    material: Value,
    #[serde(default)]
    initial_velocity: [f64; 3],
    #[serde(default)]
    angular_velocity: [f64; 3],
    #[serde(default)]
    spin_centre: Option<[f64; 3]>,
    #[serde(default)]
    particle_volume: Option<f64>,
    #[serde(default = "default_gravity")]
    gravity: [f64; 3],
    frame_dt: f64,
    #[serde(default)]
    grid_dx: Option<f64>,
    #[serde(default)]
    domain: Option<BoxSpec>,
    #[serde(default)]
    boundaries: Vec<Value>,
    #[serde(default)]
    substeps: Option<u64>,
    #[serde(default)]
    prefer_substeps: Option<u64>,
    #[serde(default)]
    allow_unstable: bool,
    #[serde(default)]
    fill_interior: Option<bool>,
    #[serde(default)]
    splat_filter: Option<f64>,
    #[serde(default)]
    merge_splats: bool,
    #[serde(default)]
    forces: Vec<Value>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMaterial {
    family: MaterialFamily,
    density: f64,
    #[serde(default)]
    youngs_modulus: Option<f64>,
    #[serde(default)]
    poisson_ratio: Option<f64>,
    #[serde(default)]
    yield_stress: Option<f64>,
    #[serde(default)]
    viscosity: Option<f64>,
    #[serde(default)]
    bulk_modulus: Option<f64>,
    #[serde(default)]
    friction_angle_deg: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGround {
    #[serde(default)]
    y: f64,
    #[serde(default)]
    condition: Condition,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHalfSpace {
    point: [f64; 3],
    normal: [f64; 3],
    #[serde(default)]
    condition: Condition,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBoxCollider {
    min: [f64; 3],
    max: [f64; 3],
    #[serde(default)]
    condition: Condition,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawForce {
    particles: Value,
    force: [f64; 3],
    #[serde(default)]
    start: f64,
    #[serde(default)]
    end: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawImpulse {
    particles: Value,
    impulse: [f64; 3],
    time: f64,
}

struct Ctx<'a> {
    file: String,
    positions: &'a Positions,
}

impl Ctx<'_> {
    fn err(
        &self,
        position: Option<Position>,
        message: String,
        hint: Option<String>,
    ) -> SimulateError {
        SimulateError::Spec(SpecError {
            file: self.file.clone(),
            position,
            message,
            hint,
        })
    }

    /// `invalid `path` = value` at the value, with the rule as hint.
    fn bad(&self, path: &str, value: &str, rule: &str) -> SimulateError {
        self.err(
            self.positions.value(path),
            format!("invalid `{path}` = {value}"),
            Some(rule.to_string()),
        )
    }

    fn positive(&self, path: &str, v: f64, unit: &str) -> Result<f64, SimulateError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.bad(path, &fmt_num(v), &format!("must be > 0 ({unit})")))
        }
    }

    fn in_parent(parent: &str) -> String {
        if parent.is_empty() {
            "at the top level".into()
        } else {
            format!("in {parent}")
        }
    }

    /// Deserialises `value` (found at `prefix`) into `T`, turning serde's message into a
    /// located one.
    fn de<T: DeserializeOwned>(&self, value: &Value, prefix: &str) -> Result<T, SimulateError> {
        serde_path_to_error::deserialize(value).map_err(|e| {
            let inner = e.path().to_string();
            let inner = inner.trim_start_matches('.');
            let full = match (prefix.is_empty(), inner.is_empty() || inner == "?") {
                (_, true) => prefix.to_string(),
                (true, false) => inner.to_string(),
                (false, false) if inner.starts_with('[') => format!("{prefix}{inner}"),
                (false, false) => format!("{prefix}.{inner}"),
            };
            self.serde_message(&full, &e.inner().to_string())
        })
    }

    fn serde_message(&self, full: &str, msg: &str) -> SimulateError {
        let quoted: Vec<String> = msg
            .split('`')
            .skip(1)
            .step_by(2)
            .map(String::from)
            .collect();
        if let Some(rest) = msg.strip_prefix("unknown field `") {
            let key = rest.split('`').next().unwrap_or_default();
            let parent = full
                .strip_suffix(&format!(".{key}"))
                .or_else(|| (full == key).then_some(""))
                .unwrap_or(full);
            let valid = &quoted[1.min(quoted.len())..];
            let hint = match suggest(key, valid) {
                Some(s) => format!("did you mean `{s}`?"),
                None => format!("valid keys: {}", valid.join(", ")),
            };
            return self.err(
                self.positions.key(&yaml::join(parent, key)),
                format!("unknown key `{key}` {}", Self::in_parent(parent)),
                Some(hint),
            );
        }
        if let Some(rest) = msg.strip_prefix("missing field `") {
            let key = rest.split('`').next().unwrap_or_default();
            return self.err(
                self.positions
                    .key(full)
                    .or(Some(Position { line: 1, col: 1 })),
                format!("missing key `{key}` {}", Self::in_parent(full)),
                None,
            );
        }
        if let Some(rest) = msg.strip_prefix("unknown variant `") {
            let word = rest.split('`').next().unwrap_or_default();
            let valid = &quoted[1.min(quoted.len())..];
            let hint = match suggest(word, valid) {
                Some(s) => format!("did you mean `{s}`? (one of {})", valid.join(", ")),
                None => format!("expected one of {}", valid.join(", ")),
            };
            return self.err(
                self.positions.value(full),
                format!("unknown value `{word}` for `{full}`"),
                Some(hint),
            );
        }
        let what = if full.is_empty() {
            String::new()
        } else {
            format!("`{full}`: ")
        };
        self.err(self.positions.value(full), format!("{what}{msg}"), None)
    }

    fn material(&self, v: &Value) -> Result<MaterialSpec, SimulateError> {
        let Value::Object(map) = v else {
            return Err(self.err(
                self.positions.value("material"),
                format!("`material` must be a mapping with `family`, `density` and the family's parameters, found {v}"),
                None,
            ));
        };
        let raw: RawMaterial = self.de(v, "material")?;
        let family = raw.family;
        let fname = family_name(family);
        let (required, optional) = family_params(family);
        for key in map.keys() {
            if key == "family" || key == "density" {
                continue;
            }
            if !required.contains(&key.as_str()) && !optional.contains(&key.as_str()) {
                let users: Vec<&str> = FAMILIES
                    .iter()
                    .filter(|f| {
                        let (r, o) = family_params(**f);
                        r.contains(&key.as_str()) || o.contains(&key.as_str())
                    })
                    .map(|f| family_name(*f))
                    .collect();
                let path = format!("material.{key}");
                return Err(self.err(
                    self.positions.key(&path),
                    format!("`{path}` is not a parameter of the {fname} family"),
                    Some(format!(
                        "`{key}` is used by {}; {fname} takes {}",
                        users.join(", "),
                        takes(family)
                    )),
                ));
            }
        }
        for key in required {
            if !map.contains_key(*key) || map[*key].is_null() {
                return Err(self.err(
                    self.positions.key("material"),
                    format!(
                        "missing key `{key}` in material: the {fname} family needs it ({})",
                        describe(key)
                    ),
                    Some(format!("{fname} takes {}", takes(family))),
                ));
            }
        }
        let m = MaterialSpec {
            family,
            density: raw.density,
            youngs_modulus: raw.youngs_modulus,
            poisson_ratio: raw.poisson_ratio,
            yield_stress: raw.yield_stress,
            viscosity: raw.viscosity,
            bulk_modulus: raw.bulk_modulus,
            friction_angle_deg: raw.friction_angle_deg,
        };
        self.positive("material.density", m.density, "kg/m^3")?;
        if let Some(e) = m.youngs_modulus {
            self.positive("material.youngs_modulus", e, "Pa")?;
        }
        if let Some(nu) = m.poisson_ratio
            && !(nu > -1.0 && nu < 0.5)
        {
            return Err(self.bad(
                "material.poisson_ratio",
                &fmt_num(nu),
                "must be in (-1, 0.5): at 0.5 the material is incompressible (λ is infinite)",
            ));
        }
        for (key, v) in [("yield_stress", m.yield_stress), ("viscosity", m.viscosity)] {
            if let Some(v) = v
                && (v.is_nan() || v < 0.0)
            {
                return Err(self.bad(&format!("material.{key}"), &fmt_num(v), "must be >= 0"));
            }
        }
        if let Some(k) = m.bulk_modulus {
            self.positive("material.bulk_modulus", k, "Pa")?;
        }
        if let Some(phi) = m.friction_angle_deg
            && !(phi > 0.0 && phi < 90.0)
        {
            return Err(self.bad(
                "material.friction_angle_deg",
                &fmt_num(phi),
                "must be in (0, 90) degrees",
            ));
        }
        Ok(m)
    }

    /// The object at `path` without its `kind` key, and the kind.
    fn tagged(
        &self,
        path: &str,
        v: &Value,
        kinds: &[&str],
    ) -> Result<(String, Value), SimulateError> {
        let list = kinds.join(", ");
        let Value::Object(map) = v else {
            return Err(self.err(
                self.positions.value(path),
                format!("`{path}` must be a mapping with a `kind` ({list}), found {v}"),
                None,
            ));
        };
        let kind = match map.get("kind") {
            Some(Value::String(s)) => s.clone(),
            Some(other) => {
                return Err(self.bad(
                    &format!("{path}.kind"),
                    &other.to_string(),
                    &format!("expected one of {list}"),
                ));
            }
            None => {
                return Err(self.err(
                    self.positions.key(path),
                    format!("missing key `kind` in {path}"),
                    Some(format!("expected one of {list}")),
                ));
            }
        };
        if !kinds.contains(&kind.as_str()) {
            let owned: Vec<String> = kinds.iter().map(|s| s.to_string()).collect();
            let hint = match suggest(&kind, &owned) {
                Some(s) => format!("did you mean `{s}`? (one of {list})"),
                None => format!("expected one of {list}"),
            };
            return Err(self.err(
                self.positions.value(&format!("{path}.kind")),
                format!("unknown kind `{kind}` in {path}"),
                Some(hint),
            ));
        }
        let mut rest: Map<String, Value> = map.clone();
        rest.remove("kind");
        Ok((kind, Value::Object(rest)))
    }

    fn check_box(&self, path: &str, b: BoxSpec) -> Result<BoxSpec, SimulateError> {
        if (0..3).any(|a| b.min[a] >= b.max[a]) {
            return Err(self.bad(
                path,
                &format!("{{min: {:?}, max: {:?}}}", b.min, b.max),
                "`min` must be below `max` on every axis",
            ));
        }
        Ok(b)
    }

    fn boundary(&self, i: usize, v: &Value) -> Result<BoundarySpec, SimulateError> {
        let path = format!("boundaries[{i}]");
        let (kind, rest) = self.tagged(&path, v, &["ground", "half_space", "box"])?;
        Ok(match kind.as_str() {
            "ground" => {
                let g: RawGround = self.de(&rest, &path)?;
                BoundarySpec::Ground {
                    y: g.y,
                    condition: g.condition,
                }
            }
            "half_space" => {
                let h: RawHalfSpace = self.de(&rest, &path)?;
                let n = glam::DVec3::from_array(h.normal);
                let len = n.length();
                if len.is_nan() || len <= 1e-12 {
                    return Err(self.bad(
                        &format!("{path}.normal"),
                        &format!("{:?}", h.normal),
                        "must be a non-zero vector (it points into the free side)",
                    ));
                }
                BoundarySpec::HalfSpace {
                    point: h.point,
                    normal: (n / len).to_array(),
                    condition: h.condition,
                }
            }
            _ => {
                let b: RawBoxCollider = self.de(&rest, &path)?;
                let aabb = self.check_box(
                    &path,
                    BoxSpec {
                        min: b.min,
                        max: b.max,
                    },
                )?;
                BoundarySpec::Box {
                    aabb,
                    condition: b.condition,
                }
            }
        })
    }

    fn particles(&self, path: &str, v: &Value) -> Result<ParticleSet, SimulateError> {
        match v {
            Value::String(s) if s == "all" => Ok(ParticleSet::All),
            Value::Array(items) => {
                if items.is_empty() {
                    return Err(self.bad(path, "[]", "list at least one particle index"));
                }
                items
                    .iter()
                    .enumerate()
                    .map(|(j, it)| {
                        it.as_u64().ok_or_else(|| {
                            self.bad(
                                &format!("{path}[{j}]"),
                                &it.to_string(),
                                "particle indices are integers >= 0 (vertex order of the input PLY)",
                            )
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()
                    .map(ParticleSet::Indices)
            }
            Value::Object(_) => {
                let b: BoxSpec = self.de(v, path)?;
                Ok(ParticleSet::Box(self.check_box(path, b)?))
            }
            other => Err(self.bad(
                path,
                &other.to_string(),
                "expected `all`, a list of particle indices, or a box {min: [x, y, z], max: [x, y, z]}",
            )),
        }
    }

    fn force(&self, i: usize, v: &Value) -> Result<ForceSpec, SimulateError> {
        let path = format!("forces[{i}]");
        let (kind, rest) = self.tagged(&path, v, &["force", "impulse"])?;
        if kind == "force" {
            let f: RawForce = self.de(&rest, &path)?;
            let particles = self.particles(&format!("{path}.particles"), &f.particles)?;
            if let Some(end) = f.end
                && end <= f.start
            {
                return Err(self.bad(
                    &format!("{path}.end"),
                    &fmt_num(end),
                    &format!("must be after `start` = {} s", fmt_num(f.start)),
                ));
            }
            Ok(ForceSpec::Force {
                particles,
                force: f.force,
                start: f.start,
                end: f.end,
            })
        } else {
            let f: RawImpulse = self.de(&rest, &path)?;
            let particles = self.particles(&format!("{path}.particles"), &f.particles)?;
            Ok(ForceSpec::Impulse {
                particles,
                impulse: f.impulse,
                time: f.time,
            })
        }
    }
}

/// `takes` list of a family for messages: `youngs_modulus, poisson_ratio (and density)`.
fn takes(f: MaterialFamily) -> String {
    let (r, o) = family_params(f);
    let mut parts: Vec<String> = r.iter().map(|s| s.to_string()).collect();
    parts.extend(o.iter().map(|s| format!("{s} (optional)")));
    format!("{} (and density)", parts.join(", "))
}

/// A number with about four significant digits (integers below 10¹² as integers, other
/// magnitudes of 10⁴ and more, or below 10⁻³, in exponent form).
pub(crate) fn short_number(v: f64) -> String {
    let a = v.abs();
    if v.fract() == 0.0 && a < 1e12 {
        format!("{v:.0}")
    } else if a >= 1e4 {
        format!("{v:.3e}")
    } else if a >= 100.0 {
        format!("{v:.1}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else if a >= 1e-3 {
        format!("{v:.4}")
    } else {
        format!("{v:.3e}")
    }
}

/// A number as the user would write it.
pub fn fmt_num(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e5 || v.abs() < 1e-3) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = "material:
  family: elastic            # elastic | elastic_fcr | plasticine | non_newtonian | newtonian | sand
  youngs_modulus: 3.0e5      # Pa
  poisson_ratio: 0.3
  density: 1000              # kg/m^3
initial_velocity: [0.5, 0.0, -0.3]   # m/s
particle_volume: 1.0e-6              # m^3; optional, default from the particle spacing
gravity: [0, -9.8, 0]
frame_dt: 0.041666666666666664       # s
grid_dx: 0.02                        # m; optional, default from the particle spacing
boundaries:
  - {kind: ground, y: 0.0, condition: sticky}    # sticky | slip | separate
";

    fn parse(text: &str) -> Result<SimSpec, String> {
        SimSpec::parse(Path::new("sim.yaml"), text).map_err(|e| e.to_string())
    }

    #[test]
    fn short_numbers_keep_about_four_digits_at_every_magnitude() {
        for (v, want) in [
            (14137.0, "14137"),
            (0.0, "0"),
            (-3.0, "-3"),
            (0.018106207251548767, "0.0181"),
            (3.955230209256568e-7, "3.955e-7"),
            (2.5, "2.50"),
            (123.456, "123.5"),
            (12345.678, "1.235e4"),
            (1e30, "1.000e30"),
            (-2.5e15, "-2.500e15"),
        ] {
            assert_eq!(short_number(v), want, "{v}");
        }
    }

    #[test]
    fn the_documented_example_parses() {
        let s = parse(EXAMPLE).unwrap();
        assert_eq!(s.material.family, MaterialFamily::Elastic);
        assert_eq!(s.material.youngs_modulus, Some(3.0e5));
        assert_eq!(s.initial_velocity, [0.5, 0.0, -0.3]);
        assert_eq!(s.grid_dx, Some(0.02));
        assert_eq!(
            s.boundaries,
            vec![BoundarySpec::Ground {
                y: 0.0,
                condition: Condition::Sticky
            }]
        );
        assert!(s.substeps.is_none() && !s.allow_unstable && s.forces.is_empty());
    }

    #[test]
    fn colliders_and_forces() {
        let text = "material: {family: sand, youngs_modulus: 1e6, poisson_ratio: 0.2, density: 1500, friction_angle_deg: 30}
frame_dt: 0.01
boundaries:
  - {kind: half_space, point: [0, 0, 0], normal: [0, 2, 0], condition: slip}
  - {kind: box, min: [0, 0, 0], max: [1, 1, 1]}
forces:
  - {kind: force, particles: [0, 2], force: [0, 1, 0], start: 0.1, end: 0.2}
  - {kind: impulse, particles: {min: [0, 0, 0], max: [1, 1, 1]}, impulse: [1, 0, 0], time: 0.05}
  - {kind: force, particles: all, force: [0, 0, 1]}
";
        let s = parse(text).unwrap();
        assert_eq!(
            s.boundaries[0],
            BoundarySpec::HalfSpace {
                point: [0.0; 3],
                normal: [0.0, 1.0, 0.0],
                condition: Condition::Slip
            }
        );
        assert!(matches!(
            s.boundaries[1],
            BoundarySpec::Box {
                condition: Condition::Sticky,
                ..
            }
        ));
        assert!(
            matches!(&s.forces[0], ForceSpec::Force { particles: ParticleSet::Indices(v), end: Some(_), .. } if v == &[0, 2])
        );
        assert!(matches!(
            &s.forces[1],
            ForceSpec::Impulse {
                particles: ParticleSet::Box(_),
                ..
            }
        ));
        assert!(matches!(
            &s.forces[2],
            ForceSpec::Force {
                particles: ParticleSet::All,
                end: None,
                ..
            }
        ));
    }

    #[test]
    fn the_splat_filter_is_a_length() {
        assert_eq!(parse(EXAMPLE).unwrap().splat_filter, 0.0);
        let s = parse(&format!("{EXAMPLE}splat_filter: 0.006\n")).unwrap();
        assert_eq!(s.splat_filter, 0.006);
        let e = parse(&format!("{EXAMPLE}splat_filter: -0.001\n")).unwrap_err();
        assert!(
            e.contains("`splat_filter`") && e.contains(">= 0 (m)"),
            "{e}"
        );
        let e = parse(&format!("{EXAMPLE}splat_filter: .nan\n")).unwrap_err();
        assert!(e.contains("non-finite") && e.contains("line 13"), "{e}");
    }

    #[test]
    fn located_errors() {
        let e = parse(&EXAMPLE.replace("poisson_ratio: 0.3", "poisson_ratio: 0.5")).unwrap_err();
        assert!(
            e.contains("sim.yaml")
                && e.contains("`material.poisson_ratio` = 0.5")
                && e.contains("line 4:18"),
            "{e}"
        );
        let e = parse(&EXAMPLE.replace("  density: 1000", "  densty: 1000")).unwrap_err();
        assert!(
            e.contains("unknown key `densty` in material at line 5:3")
                && e.contains("did you mean `density`?"),
            "{e}"
        );
        let e = parse(&EXAMPLE.replace("frame_dt:", "frame_tdt:")).unwrap_err();
        assert!(
            e.contains("unknown key `frame_tdt` at the top level at line 9:1")
                && e.contains("`frame_dt`"),
            "{e}"
        );
        let e = parse(&EXAMPLE.replace("family: elastic ", "family: elastc ")).unwrap_err();
        assert!(
            e.contains("unknown value `elastc`")
                && e.contains("did you mean `elastic`?")
                && e.contains("line 2:11"),
            "{e}"
        );
        let e = parse(&EXAMPLE.replace("condition: sticky", "condition: stiky")).unwrap_err();
        assert!(
            e.contains("boundaries[0].condition")
                && e.contains("did you mean `sticky`?")
                && e.contains("line 12:"),
            "{e}"
        );
        let e =
            parse(&EXAMPLE.replace("kind: ground, y: 0.0", "kind: ground, yy: 0.0")).unwrap_err();
        assert!(
            e.contains("unknown key `yy` in boundaries[0]") && e.contains("did you mean `y`?"),
            "{e}"
        );
        let e = parse(&EXAMPLE.replace("kind: ground", "kind: grund")).unwrap_err();
        assert!(
            e.contains("unknown kind `grund`") && e.contains("did you mean `ground`?"),
            "{e}"
        );
        let e =
            parse(&EXAMPLE.replace("frame_dt: 0.041666666666666664", "frame_dt: -1")).unwrap_err();
        assert!(e.contains("invalid `frame_dt` = -1 at line 9:11"), "{e}");
        let e = parse(&EXAMPLE.replace(
            "initial_velocity: [0.5, 0.0, -0.3]",
            "initial_velocity: [0.5, 0.0]",
        ))
        .unwrap_err();
        assert!(
            e.contains("`initial_velocity`") && e.contains("line 6:"),
            "{e}"
        );
        let e = parse(
            "material: {family: elastic, youngs_modulus: 1e5, poisson_ratio: 0.3, density: 1}\n",
        )
        .unwrap_err();
        assert!(e.contains("missing key `frame_dt` at the top level"), "{e}");
        let e = parse("frame_dt: 0.1\nmaterial: {family: newtonian, viscosity: 1, bulk_modulus: 1e5, density: 1000}\nforces:\n  - {kind: force, particles: [0, -1], force: [0, 0, 0]}\n").unwrap_err();
        assert!(
            e.contains("`forces[0].particles[1]` = -1") && e.contains("line 4:"),
            "{e}"
        );
    }

    #[test]
    fn nested_and_type_errors() {
        let e = parse(&format!(
            "{EXAMPLE}domain: {{min: [0, 0, 0], mx: [1, 1, 1]}}\n"
        ))
        .unwrap_err();
        assert!(
            e.contains("unknown key `mx` in domain at line 13:")
                && e.contains("did you mean `max`?"),
            "{e}"
        );
        let e =
            parse(&EXAMPLE.replace("youngs_modulus: 3.0e5", "youngs_modulus: stiff")).unwrap_err();
        assert!(
            e.contains("`material.youngs_modulus`: invalid type: string \"stiff\"")
                && e.contains("line 3:19"),
            "{e}"
        );
        let e = parse(&format!("{EXAMPLE}substeps: 0\n")).unwrap_err();
        assert!(e.contains("invalid `substeps` = 0 at line 13:11"), "{e}");
        let e = parse(&format!("{EXAMPLE}forces:\n  - {{kind: force, particles: [0], force: [0, 1, 0], start: 0.2, end: 0.1}}\n")).unwrap_err();
        assert!(
            e.contains("invalid `forces[0].end` = 0.1") && e.contains("after `start` = 0.2 s"),
            "{e}"
        );
        let e = parse("").unwrap_err();
        assert!(
            e.contains("sim.yaml: a simulation file is a mapping"),
            "{e}"
        );
    }

    #[test]
    fn family_parameter_checks() {
        let base = "frame_dt: 0.1\nmaterial:\n  family: FAM\n  density: 1000\n";
        let e = parse(
            &(base.replace("FAM", "newtonian")
                + "  viscosity: 1\n  bulk_modulus: 1e5\n  youngs_modulus: 1e5\n"),
        )
        .unwrap_err();
        assert!(
            e.contains(
                "`material.youngs_modulus` is not a parameter of the newtonian family at line 7:3"
            ),
            "{e}"
        );
        assert!(
            e.contains("used by elastic, elastic_fcr, plasticine, non_newtonian, sand"),
            "{e}"
        );
        let e = parse(
            &(base.replace("FAM", "plasticine") + "  youngs_modulus: 1e5\n  poisson_ratio: 0.3\n"),
        )
        .unwrap_err();
        assert!(
            e.contains("missing key `yield_stress` in material: the plasticine family needs it"),
            "{e}"
        );
        let e = parse(
            &(base.replace("FAM", "elastic") + "  youngs_modulus: 0\n  poisson_ratio: 0.3\n"),
        )
        .unwrap_err();
        assert!(
            e.contains("invalid `material.youngs_modulus` = 0 at line 5:19")
                && e.contains("must be > 0"),
            "{e}"
        );
        let s = parse(
            &(base.replace("FAM", "plasticine")
                + "  youngs_modulus: 1e5\n  poisson_ratio: 0.3\n  yield_stress: 2e3\n"),
        )
        .unwrap();
        assert_eq!(
            s.material.mpm_family(),
            pipe_mpm::Family::VonMises {
                yield_stress: 2e3,
                eta: 0.0
            }
        );
    }
}
