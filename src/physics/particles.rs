//! The `material_particles` table (`particles.arrow` of the `material` stage): the simulated
//! particles at frame 0 with their mass, volume, material and initial velocity
//! (ARCHITECTURE §5). Particles that are Gaussians come first, `id` joining `gaussians.id`;
//! fillers follow with `id = null`.

use std::path::Path;
use std::sync::Arc;

use arrow_array::{Array, BooleanArray, Float32Array, Float64Array, RecordBatch, UInt32Array};
use arrow_schema::{DataType, Field, Schema};
use glam::DVec3;

use super::object::Object;
use super::params::{MaterialValues, Param};
use crate::scene::table::{self, Table, TableError, column};

/// One row per simulated particle.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MaterialParticles {
    /// The id of the first Gaussian the particle carries (the others of its voxel ride it too,
    /// `simulate::skin`), `None` for a filler.
    pub id: Vec<Option<u32>>,
    /// Whether the particle carries Gaussians or only simulates (a filler).
    pub rendered: Vec<bool>,
    /// Position at frame 0 (m).
    pub x: Vec<[f32; 3]>,
    /// Initial velocity (m/s).
    pub v0: Vec<[f32; 3]>,
    /// Mass (kg) and volume (m³).
    pub mass_kg: Vec<f64>,
    pub volume_m3: Vec<f64>,
    /// Young's modulus (Pa) and Poisson's ratio; `None` for a fluid.
    pub youngs_pa: Vec<Option<f64>>,
    pub poisson: Vec<Option<f64>>,
    /// The family's other parameters, `None` where it has none: yield stress (Pa), viscosity
    /// (Pa·s), bulk modulus (Pa), friction angle (degrees).
    pub yield_stress_pa: Vec<Option<f64>>,
    pub viscosity_pa_s: Vec<Option<f64>>,
    pub bulk_pa: Vec<Option<f64>>,
    pub friction_deg: Vec<Option<f64>>,
}

impl Table for MaterialParticles {
    const NAME: &'static str = "material_particles";
    const VERSION: u32 = 1;

    fn schema() -> Schema {
        let f32s = |name: &str| Field::new(name, DataType::Float32, false);
        let f64n = |name: &str| Field::new(name, DataType::Float64, true);
        Schema::new(vec![
            Field::new("id", DataType::UInt32, true),
            Field::new("rendered", DataType::Boolean, false),
            f32s("x"),
            f32s("y"),
            f32s("z"),
            f32s("vx"),
            f32s("vy"),
            f32s("vz"),
            Field::new("mass_kg", DataType::Float64, false),
            Field::new("volume_m3", DataType::Float64, false),
            f64n("youngs_pa"),
            f64n("poisson"),
            f64n("yield_stress_pa"),
            f64n("viscosity_pa_s"),
            f64n("bulk_pa"),
            f64n("friction_deg"),
        ])
        .with_metadata([("schema_version".to_string(), Self::VERSION.to_string())])
    }

    fn to_batch(&self) -> RecordBatch {
        let f32c = |v: &[[f32; 3]], a: usize| -> Arc<dyn Array> {
            Arc::new(Float32Array::from_iter_values(v.iter().map(|p| p[a])))
        };
        let f64o = |v: &[Option<f64>]| -> Arc<dyn Array> {
            Arc::new(Float64Array::from_iter(v.iter().copied()))
        };
        RecordBatch::try_new(
            Arc::new(Self::schema()),
            vec![
                Arc::new(UInt32Array::from_iter(self.id.iter().copied())),
                Arc::new(BooleanArray::from(self.rendered.clone())),
                f32c(&self.x, 0),
                f32c(&self.x, 1),
                f32c(&self.x, 2),
                f32c(&self.v0, 0),
                f32c(&self.v0, 1),
                f32c(&self.v0, 2),
                Arc::new(Float64Array::from(self.mass_kg.clone())),
                Arc::new(Float64Array::from(self.volume_m3.clone())),
                f64o(&self.youngs_pa),
                f64o(&self.poisson),
                f64o(&self.yield_stress_pa),
                f64o(&self.viscosity_pa_s),
                f64o(&self.bulk_pa),
                f64o(&self.friction_deg),
            ],
        )
        .expect("columns match the schema")
    }

    fn from_batch(b: &RecordBatch, _path: &Path) -> Result<Self, TableError> {
        let n = b.num_rows();
        let f32c = |name: &str| column::<Float32Array>(b, name).values().to_vec();
        let zip3 = |a: Vec<f32>, b: Vec<f32>, c: Vec<f32>| -> Vec<[f32; 3]> {
            (0..a.len()).map(|i| [a[i], b[i], c[i]]).collect()
        };
        let f64o = |name: &str| {
            let c = column::<Float64Array>(b, name);
            (0..n)
                .map(|i| c.is_valid(i).then(|| c.value(i)))
                .collect::<Vec<_>>()
        };
        let id = column::<UInt32Array>(b, "id");
        let rendered = column::<BooleanArray>(b, "rendered");
        Ok(Self {
            id: (0..n)
                .map(|i| id.is_valid(i).then(|| id.value(i)))
                .collect(),
            rendered: (0..n).map(|i| rendered.value(i)).collect(),
            x: zip3(f32c("x"), f32c("y"), f32c("z")),
            v0: zip3(f32c("vx"), f32c("vy"), f32c("vz")),
            mass_kg: column::<Float64Array>(b, "mass_kg").values().to_vec(),
            volume_m3: column::<Float64Array>(b, "volume_m3").values().to_vec(),
            youngs_pa: f64o("youngs_pa"),
            poisson: f64o("poisson"),
            yield_stress_pa: f64o("yield_stress_pa"),
            viscosity_pa_s: f64o("viscosity_pa_s"),
            bulk_pa: f64o("bulk_pa"),
            friction_deg: f64o("friction_deg"),
        })
    }
}

/// Writes the particles of `object` under `material` (with per-particle E and ν from `moduli`
/// when given) and initial velocities `v0` (m/s).
pub fn write(
    path: &Path,
    object: &Object,
    material: &MaterialValues,
    moduli: Option<&super::rollout::Moduli>,
    v0: &[DVec3],
) -> Result<(), TableError> {
    let n = object.particles();
    let r = object.carriers();
    let mut first = vec![None; r];
    for (g, &c) in object.skin().carrier().iter().enumerate().rev() {
        first[c as usize] = Some(object.gaussians.id[g]);
    }
    let fluid = matches!(
        material.family,
        crate::pipeline::spec::MaterialFamily::Newtonian
    );
    let each = |p: Param| vec![material.get(p); n];
    let t = MaterialParticles {
        id: (0..n)
            .map(|i| if i < r { first[i] } else { None })
            .collect(),
        rendered: (0..n).map(|i| i < r).collect(),
        x: object
            .body
            .state
            .x
            .iter()
            .map(|p| p.as_vec3().to_array())
            .collect(),
        v0: v0.iter().map(|v| v.as_vec3().to_array()).collect(),
        mass_kg: object.body.material.mass.clone(),
        volume_m3: object.body.material.volume.clone(),
        youngs_pa: match (fluid, moduli) {
            (true, _) => vec![None; n],
            (false, Some(m)) => m.e.iter().map(|v| Some(*v)).collect(),
            (false, None) => each(Param::E),
        },
        poisson: match (fluid, moduli) {
            (true, _) => vec![None; n],
            (false, Some(m)) => m.nu.iter().map(|v| Some(*v)).collect(),
            (false, None) => each(Param::Nu),
        },
        yield_stress_pa: each(Param::YieldStress),
        viscosity_pa_s: each(Param::Viscosity),
        bulk_pa: each(Param::BulkModulus),
        friction_deg: each(Param::FrictionAngle),
    };
    table::write(path, &t)
}
