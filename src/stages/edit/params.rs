//! The parameters of one edit (`stages.edit.<name>`), as written in the pipeline file, and
//! their checks (each error names the field and the value; the runner adds the file and line).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::physics::fit::PrecisionParam;
use crate::physics::object::Resolution;
use crate::physics::params::Param;
use crate::pipeline::spec::{BoundaryItem, MaterialFamily};
use crate::pipeline::stage::ParamError;

/// Parameters of one edit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EditParams {
    /// Forces and impulses, each on the Gaussians a selection picks (several may act).
    #[serde(default)]
    pub interactions: Vec<Interaction>,
    /// Start from the learned initial velocity (`material`'s, else `velocity`'s); by default
    /// the object starts at rest.
    #[serde(default)]
    pub keep_velocity: bool,
    /// Changes to the learned material (or, without a `material` stage, the material itself).
    #[serde(default)]
    pub material: MaterialEdit,
    /// Gravity (m/s²); default: the scene's.
    #[serde(default)]
    pub gravity: Option<[f64; 3]>,
    /// What acts on the object besides gravity, in the scene's `boundaries` syntax; default:
    /// the scene's (`[]`: none).
    #[serde(default)]
    pub boundaries: Option<Vec<BoundaryItem>>,
    /// Output frames, frame 0 (the canonical state) included; default: as many as the capture.
    #[serde(default)]
    pub frames: Option<u32>,
    /// Time between output frames (s); default: the capture's.
    #[serde(default)]
    pub frame_dt: Option<f64>,
    /// Views rendered every frame: `{view: <camera of the capture>}` or `{orbit: {...}}`;
    /// default: the scene's test views (its first camera without any); `[]` renders nothing.
    #[serde(default)]
    pub cameras: Option<Vec<CameraSpec>>,
    /// Draw an arrow where and how each force (red) and impulse (orange) acts.
    #[serde(default)]
    pub overlay_forces: bool,
    /// Write every frame's Gaussians as a 3DGS PLY (`splats/splats_NNNN.ply`).
    #[serde(default = "yes")]
    pub splats: bool,
    /// Re-light the moved Gaussians (solids): the irradiance of each surface normal, fitted
    /// to the shading the warm-up baked into the colours, stays in the world when the body
    /// turns or flattens ([`crate::scene::shading`]); also in the written splats.
    #[serde(default = "yes")]
    pub relight: bool,
    /// Hold the simulated part where it meets Gaussians that do not simulate (a PhysDreamer
    /// scene's moving part on its still object): the grid nodes within a cell of every still
    /// Gaussian that has a simulated particle within two cells are held still, as
    /// PhysDreamer freezes the grid next to the still points. No effect when every Gaussian
    /// simulates.
    #[serde(default = "yes")]
    pub anchor: bool,
    /// Grid cells across the object's largest extent; default: the `material` stage's grid
    /// (its `dx` when it has one, else its `cells`; 24 cells without a `material` stage).
    #[serde(default)]
    pub cells: Option<f64>,
    /// Precision of the simulation.
    #[serde(default)]
    pub precision: PrecisionParam,
    /// Milliseconds per GIF frame; default: `frame_dt` (real time), at least 20.
    #[serde(default)]
    pub gif_ms: Option<u32>,
    /// Background colour (RGB in [0, 1]) of orbit views (capture views show their plate).
    #[serde(default = "white")]
    pub background: [f32; 3],
}

fn yes() -> bool {
    true
}

fn white() -> [f32; 3] {
    [1.0; 3]
}

/// A force or an impulse on the material a selection picks. The vector is the **total**
/// over the selection, spread over its particles in proportion to their mass (every selected
/// particle gets the same acceleration `F / M`, `M` the selection's mass).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Interaction {
    /// A constant total force (N) while `start ≤ t < end` (s).
    Force {
        /// The material it acts on.
        select: Selection,
        /// Total force (N).
        force: [f64; 3],
        /// Start (s from frame 0).
        #[serde(default)]
        start: f64,
        /// End (s); default: the end of the edit.
        #[serde(default)]
        end: Option<f64>,
    },
    /// A total impulse (N·s) at time `time` (s).
    Impulse {
        /// The material it acts on.
        select: Selection,
        /// Total impulse (N·s).
        impulse: [f64; 3],
        /// When (s from frame 0).
        #[serde(default)]
        time: f64,
    },
}

impl Interaction {
    /// The selection.
    pub fn select(&self) -> &Selection {
        match self {
            Interaction::Force { select, .. } | Interaction::Impulse { select, .. } => select,
        }
    }
}

/// Which Gaussians an interaction picks, in the canonical (frame 0) state. The force acts on
/// the material of the region: the picked Gaussians and the filler particles inside it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Selection {
    /// Within `radius` (m) of `center` (m).
    Sphere {
        /// Centre (m).
        center: [f64; 3],
        /// Radius (m).
        radius: f64,
    },
    /// Inside the box (m).
    Box {
        /// Lower corner (m).
        min: [f64; 3],
        /// Upper corner (m).
        max: [f64; 3],
    },
    /// The `count` Gaussians nearest to `point` (m); the region is the ball around `point`
    /// reaching the farthest of them.
    Nearest {
        /// The point (m).
        point: [f64; 3],
        /// How many.
        count: u32,
    },
}

/// A camera the edit is rendered from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum CameraSpec {
    /// A camera of the capture (its index), over its background plate.
    View(u16),
    /// A camera circling the object, looking at `center`, over `background`.
    Orbit(OrbitSpec),
}

/// A camera that circles `center` about the scene's up axis (against the scene's gravity; +y
/// without gravity), one turn every `frames` output frames, looking at `center`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct OrbitSpec {
    /// What it looks at (m); default: the object's centre of mass at frame 0.
    #[serde(default)]
    pub center: Option<[f64; 3]>,
    /// Distance from `center` (m); default: the object's bounding sphere fills 60 % of the
    /// view's height.
    #[serde(default)]
    pub radius: Option<f64>,
    /// Height above the horizontal plane through `center` (degrees).
    #[serde(default = "elevation")]
    pub elevation_deg: f64,
    /// Output frames per turn (`0`: the camera stays at `start_deg`); default: the edit's
    /// frame count (one turn).
    #[serde(default)]
    pub frames: Option<u32>,
    /// Azimuth at frame 0 (degrees, from the +x axis towards +z for a +y up axis).
    #[serde(default)]
    pub start_deg: f64,
    /// Image width and height (pixels).
    #[serde(default = "orbit_size")]
    pub size: [u32; 2],
    /// Vertical field of view (degrees).
    #[serde(default = "fov")]
    pub fov_deg: f64,
}

fn elevation() -> f64 {
    20.0
}

fn orbit_size() -> [u32; 2] {
    [256, 256]
}

fn fov() -> f64 {
    40.0
}

/// A material value: a new value, or a factor on the learned one (`{scale: 0.1}`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, JsonSchema)]
#[serde(untagged, deny_unknown_fields)]
pub enum Change {
    /// The new value (SI units, degrees).
    Value(f64),
    /// A factor on the learned value.
    Scale {
        /// The factor (> 0).
        scale: f64,
    },
}

impl<'de> Deserialize<'de> for Change {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::{Error, MapAccess, Visitor};
        struct ChangeVisitor;
        impl<'de> Visitor<'de> for ChangeVisitor {
            type Value = Change;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a number (the new value) or {scale: factor}")
            }
            fn visit_f64<E: Error>(self, v: f64) -> Result<Change, E> {
                Ok(Change::Value(v))
            }
            fn visit_i64<E: Error>(self, v: i64) -> Result<Change, E> {
                Ok(Change::Value(v as f64))
            }
            fn visit_u64<E: Error>(self, v: u64) -> Result<Change, E> {
                Ok(Change::Value(v as f64))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<Change, A::Error> {
                let mut scale = None;
                while let Some(k) = m.next_key::<String>()? {
                    if k != "scale" {
                        return Err(A::Error::unknown_field(&k, &["scale"]));
                    }
                    scale = Some(m.next_value::<f64>()?);
                }
                scale
                    .map(|scale| Change::Scale { scale })
                    .ok_or_else(|| A::Error::missing_field("scale"))
            }
        }
        d.deserialize_any(ChangeVisitor)
    }
}

/// The `material:` block of an edit: the simulation file's keys, each a [`Change`].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MaterialEdit {
    /// Another family (its parameters the learned material lacks must be given).
    #[serde(default)]
    pub family: Option<MaterialFamily>,
    /// Young's modulus E (Pa).
    #[serde(default)]
    pub youngs_modulus: Option<Change>,
    /// Poisson's ratio ν.
    #[serde(default)]
    pub poisson_ratio: Option<Change>,
    /// Yield stress (Pa).
    #[serde(default)]
    pub yield_stress: Option<Change>,
    /// Viscosity (Pa·s).
    #[serde(default)]
    pub viscosity: Option<Change>,
    /// Bulk modulus κ (Pa).
    #[serde(default)]
    pub bulk_modulus: Option<Change>,
    /// Friction angle (degrees).
    #[serde(default)]
    pub friction_angle_deg: Option<Change>,
    /// Density (kg/m³); default the scene's.
    #[serde(default)]
    pub density: Option<Change>,
}

impl MaterialEdit {
    /// The parameter changes, with their file keys.
    pub fn changes(&self) -> Vec<(&'static str, Param, Change)> {
        [
            ("youngs_modulus", Param::E, self.youngs_modulus),
            ("poisson_ratio", Param::Nu, self.poisson_ratio),
            ("yield_stress", Param::YieldStress, self.yield_stress),
            ("viscosity", Param::Viscosity, self.viscosity),
            ("bulk_modulus", Param::BulkModulus, self.bulk_modulus),
            (
                "friction_angle_deg",
                Param::FrictionAngle,
                self.friction_angle_deg,
            ),
        ]
        .into_iter()
        .filter_map(|(k, p, c)| c.map(|c| (k, p, c)))
        .collect()
    }
}

/// The file key of a material parameter.
pub fn param_key(p: Param) -> &'static str {
    match p {
        Param::E => "youngs_modulus",
        Param::Nu => "poisson_ratio",
        Param::YieldStress => "yield_stress",
        Param::Viscosity => "viscosity",
        Param::BulkModulus => "bulk_modulus",
        Param::FrictionAngle => "friction_angle_deg",
    }
}

fn bad<T>(path: impl Into<String>, message: String) -> Result<T, ParamError> {
    Err(ParamError {
        path: path.into(),
        message,
    })
}

fn finite3(path: &str, v: [f64; 3]) -> Result<(), ParamError> {
    if v.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        bad(path, format!("must be finite, found {v:?}"))
    }
}

/// Checks that serde cannot express: ranges, finiteness, windows.
pub fn validate(p: &EditParams) -> Result<(), ParamError> {
    for (i, it) in p.interactions.iter().enumerate() {
        let at = |k: &str| format!("interactions[{i}].{k}");
        match it.select() {
            Selection::Sphere { center, radius } => {
                finite3(&at("select.sphere.center"), *center)?;
                if !(radius.is_finite() && *radius > 0.0) {
                    return bad(
                        at("select.sphere.radius"),
                        format!("must be > 0 (m), found {radius}"),
                    );
                }
            }
            Selection::Box { min, max } => {
                finite3(&at("select.box.min"), *min)?;
                finite3(&at("select.box.max"), *max)?;
                if (0..3).any(|k| min[k] > max[k]) {
                    return bad(
                        at("select.box"),
                        format!("`min` {min:?} must not exceed `max` {max:?} on any axis"),
                    );
                }
            }
            Selection::Nearest { point, count } => {
                finite3(&at("select.nearest.point"), *point)?;
                if *count == 0 {
                    return bad(at("select.nearest.count"), "must be at least 1".into());
                }
            }
        }
        match it {
            Interaction::Force {
                force, start, end, ..
            } => {
                finite3(&at("force"), *force)?;
                if !(start.is_finite() && *start >= 0.0) {
                    return bad(at("start"), format!("must be >= 0 (s), found {start}"));
                }
                if let Some(e) = end
                    && !(e.is_finite() && e > start)
                {
                    return bad(
                        at("end"),
                        format!("must be after `start` = {start} s, found {e}"),
                    );
                }
            }
            Interaction::Impulse { impulse, time, .. } => {
                finite3(&at("impulse"), *impulse)?;
                if !(time.is_finite() && *time >= 0.0) {
                    return bad(at("time"), format!("must be >= 0 (s), found {time}"));
                }
            }
        }
    }
    for (key, _, change) in p.material.changes() {
        check_change(key, change)?;
    }
    if let Some(d) = p.material.density {
        check_change("density", d)?;
    }
    if let Some(g) = p.gravity {
        finite3("gravity", g)?;
    }
    if let Some(f) = p.frames
        && !(2..=u32::from(u16::MAX) + 1).contains(&f)
    {
        return bad(
            "frames",
            format!("must be from 2 to 65536 (frame 0 included), found {f}"),
        );
    }
    if let Some(dt) = p.frame_dt
        && !(dt.is_finite() && dt > 0.0)
    {
        return bad("frame_dt", format!("must be > 0 (s), found {dt}"));
    }
    if let Some(c) = p.cells
        && let Err((field, message)) = Resolution::check(c, None)
    {
        return bad(field, message);
    }
    if let Some(ms) = p.gif_ms
        && !(1..=10_000).contains(&ms)
    {
        return bad("gif_ms", format!("must be in 1..=10000, found {ms}"));
    }
    if !p.background.iter().all(|c| (0.0..=1.0).contains(c)) {
        return bad(
            "background",
            format!("each channel must be in [0, 1], found {:?}", p.background),
        );
    }
    for (i, cam) in p.cameras.iter().flatten().enumerate() {
        let CameraSpec::Orbit(o) = cam else { continue };
        let at = |k: &str| format!("cameras[{i}].orbit.{k}");
        if let Some(c) = o.center {
            finite3(&at("center"), c)?;
        }
        if let Some(r) = o.radius
            && !(r.is_finite() && r > 0.0)
        {
            return bad(at("radius"), format!("must be > 0 (m), found {r}"));
        }
        if !(o.elevation_deg.is_finite() && o.elevation_deg.abs() <= 89.0) {
            return bad(
                at("elevation_deg"),
                format!("must be in [-89, 89] degrees, found {}", o.elevation_deg),
            );
        }
        if !o.start_deg.is_finite() {
            return bad(
                at("start_deg"),
                format!("must be finite, found {}", o.start_deg),
            );
        }
        if o.size.iter().any(|&s| !(1..=4096).contains(&s)) {
            return bad(
                at("size"),
                format!(
                    "width and height must be 1 to 4096 pixels, found {:?}",
                    o.size
                ),
            );
        }
        if !(o.fov_deg.is_finite() && o.fov_deg > 1.0 && o.fov_deg < 170.0) {
            return bad(
                at("fov_deg"),
                format!("must be in (1, 170) degrees, found {}", o.fov_deg),
            );
        }
    }
    Ok(())
}

fn check_change(key: &str, change: Change) -> Result<(), ParamError> {
    let path = format!("material.{key}");
    match change {
        Change::Scale { scale } if !(scale.is_finite() && scale > 0.0) => bad(
            format!("{path}.scale"),
            format!("must be > 0, found {scale}"),
        ),
        Change::Value(v) if key == "poisson_ratio" && !(v > -1.0 && v < 0.5) => {
            bad(path, format!("must be in (-1, 0.5), found {v}"))
        }
        Change::Value(v) if key == "friction_angle_deg" && !(v > 0.0 && v < 90.0) => {
            bad(path, format!("must be in (0, 90) degrees, found {v}"))
        }
        Change::Value(v)
            if matches!(key, "yield_stress" | "viscosity") && !(v.is_finite() && v >= 0.0) =>
        {
            bad(path, format!("must be >= 0, found {v}"))
        }
        Change::Value(v)
            if matches!(key, "youngs_modulus" | "bulk_modulus" | "density")
                && !(v.is_finite() && v > 0.0) =>
        {
            bad(path, format!("must be > 0, found {v}"))
        }
        _ => Ok(()),
    }
}
