//! A per-particle material field (the seed paper's §3.2, eq. 8): a triplane + MLP
//! ([`pipe_field`]) maps a particle's rest position (m) to its `log10 E` and its encoded `ν`
//! (the global model's bounded map, [`Param::Nu`]'s encoding), so parts of one object can differ
//! in stiffness. The field's box is the particles' rest box grown by [`MARGIN`] of its largest
//! extent on every side.
//!
//! Chain rule from the rollout's per-particle gradients ([`crate::physics::rollout::Moduli`]) to
//! the field's outputs: `∂L/∂(log10 E_p) = ∂L/∂E_p · E_p · ln 10`,
//! `∂L/∂u_p = ∂L/∂ν_p · dν/du(u_p)`.

use std::path::Path;
use std::sync::Arc;

use arrow_array::{Float64Array, RecordBatch, StringArray, UInt32Array};
use arrow_schema::{DataType, Field as ArrowField, Schema};
use pipe_field::{Field, FieldConfig, FieldError, FieldWeights};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::field_parts::Parts;
use super::params::{MaterialValues, Param};
use super::rollout::{Moduli, Truncate};
use crate::scene::table::{self, Table, TableError, column};

/// The field's box around the rest positions: this fraction of their largest extent on every
/// side (so the outermost particles do not sit on the planes' last nodes).
pub const MARGIN: f64 = 0.05;

/// Settings of `material: {model: field}` (the `field:` block of the stage).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FieldSettings {
    /// Nodes per plane side (the paper: 24).
    #[serde(default = "resolution")]
    pub resolution: usize,
    /// Feature channels per plane node (summed over the three planes).
    #[serde(default = "channels")]
    pub channels: usize,
    /// Width of the MLP's hidden layers.
    #[serde(default = "hidden")]
    pub hidden: usize,
    /// Hidden layers of the MLP.
    #[serde(default = "layers")]
    pub layers: usize,
    /// Weight of the planes' total variation (eq. 8): larger is smoother.
    #[serde(default = "tv_weight")]
    pub tv_weight: f64,
    /// Epochs of the field after the global fit it starts from (default: the stage's `epochs`).
    #[serde(default)]
    pub epochs: Option<u32>,
    /// Adam's first step for the planes and the MLP (decays to `lr_final`). Every weight moves
    /// by about this much, so an output can move by many times it (0.03 moved the demo's
    /// log10 E by 0.3 in the first epoch and raised the loss).
    #[serde(default = "field_lr")]
    pub lr: f64,
    /// Adam's last step.
    #[serde(default = "field_lr_final")]
    pub lr_final: f64,
    /// Seed of the planes' and the MLP's initial weights.
    #[serde(default)]
    pub seed: u64,
    /// How far back a frame's loss is differentiated for the field: `none` (default), one
    /// Adam step an epoch along the whole rollout's gradient; `frame`, a step after every
    /// frame's truncated gradient (the seed method's online descent). On a generated
    /// two-material bar the per-frame steps hardly moved the field at a safe rate and were
    /// noisy at a larger one; the whole gradient separated the halves.
    #[serde(default = "field_truncate")]
    pub truncate: Truncate,
    /// The parameters that vary over the particles (`E` and/or `nu`, among the stage's
    /// learned ones); the others learned stay global and keep stepping. Default `[E]`: on a
    /// generated two-material bar a field of ν as well traded E against ν (ν drifted to 0.39,
    /// the soft half's E rose 3×) where an E field with a global ν fitted the frames better.
    #[serde(default = "vary")]
    pub vary: Vec<Param>,
    /// `model: auto` groups a field that wins into 2 to this many parts (natural breaks of its
    /// `log10 E`, [`crate::physics::field_parts`]), each part one material whose E is fitted
    /// on the field's views and frames; of these models and the field, the simplest that wins
    /// on the held-out data and on the second grid (`auto.regrid`), within `auto.margin` of
    /// the best that does, is kept. 0 or 1 tries no parts.
    #[serde(default = "parts")]
    pub parts: usize,
    /// Descent iterations of each parts model (default: the stage's `epochs`).
    #[serde(default)]
    pub parts_epochs: Option<u32>,
}

fn parts() -> usize {
    3
}

/// The most parts `field.parts` may ask for.
pub const MAX_PARTS: usize = 8;

fn vary() -> Vec<Param> {
    vec![Param::E]
}

fn field_truncate() -> Truncate {
    Truncate::None
}

fn resolution() -> usize {
    24
}
fn channels() -> usize {
    16
}
fn hidden() -> usize {
    64
}
fn layers() -> usize {
    2
}
fn tv_weight() -> f64 {
    1e-3
}
fn field_lr() -> f64 {
    0.005
}
fn field_lr_final() -> f64 {
    0.0005
}

impl Default for FieldSettings {
    fn default() -> Self {
        Self {
            resolution: resolution(),
            channels: channels(),
            hidden: hidden(),
            layers: layers(),
            tv_weight: tv_weight(),
            epochs: None,
            lr: field_lr(),
            lr_final: field_lr_final(),
            seed: 0,
            truncate: field_truncate(),
            vary: vary(),
            parts: parts(),
            parts_epochs: None,
        }
    }
}

impl FieldSettings {
    /// The field's configuration for `outputs` outputs.
    pub fn config(&self, outputs: usize) -> FieldConfig {
        FieldConfig {
            resolution: self.resolution,
            channels: self.channels,
            hidden: self.hidden,
            layers: self.layers,
            tv_weight: self.tv_weight,
            ..FieldConfig::material(outputs)
        }
    }
}

/// The field and what its outputs mean.
#[derive(Debug, Clone, PartialEq)]
pub struct MaterialField {
    /// The triplane + MLP.
    pub field: Field,
    /// The parameters it outputs, in output order: [`Param::E`] (as `log10 E`) and/or
    /// [`Param::Nu`] (encoded).
    pub outputs: Vec<Param>,
    /// Rest positions of the particles it is evaluated at (m).
    pub points: Vec<[f64; 3]>,
    /// `log10 E` of the global fit the field started from: the centre of E's bounded map.
    pub log10_e_centre: f64,
    /// The field's values grouped into a few materials ([`Parts`]), when `model: auto` kept
    /// them: each point then takes its part's E.
    pub parts: Option<Parts>,
}

/// How far (decades) a particle's E may go from the global fit's: `log10 E = c + R·tanh((y −
/// c)/R)` for the field's output `y`, so a particle the frames hardly constrain cannot run
/// off to a modulus no material has (unbounded, 5 % of a bar's particles fell to 25 Pa).
pub const E_RANGE_DECADES: f64 = 2.0;

/// The output the field holds for `p` at value `v` (E relative to the centre `c`).
fn encode(p: Param, v: f64) -> f64 {
    match p {
        Param::E => v.log10(),
        _ => p.encode(v),
    }
}

/// The value of `p` from its output `y` (E through the bounded map about `c`).
fn decode(p: Param, y: f64, c: f64) -> f64 {
    match p {
        Param::E => 10f64.powf(c + E_RANGE_DECADES * ((y - c) / E_RANGE_DECADES).tanh()),
        _ => p.decode(y),
    }
}

impl MaterialField {
    /// A field over `points` (rest positions, m) that outputs, everywhere, `start`'s value of
    /// each of `outputs` (E and/or ν): the field starts exactly at the global model.
    ///
    /// # Errors
    /// A degenerate box (all points in a plane) or a bad setting, named.
    pub fn starting_at(
        settings: &FieldSettings,
        points: Vec<[f64; 3]>,
        outputs: Vec<Param>,
        start: &MaterialValues,
    ) -> Result<Self, FieldError> {
        let extent = largest_extent(&points);
        let domain = pipe_field::Domain::around(&points, MARGIN * extent)?;
        let value: Vec<f64> = outputs
            .iter()
            .map(|p| encode(*p, start.get(*p).unwrap_or(f64::NAN)))
            .collect();
        let log10_e_centre = start.get(Param::E).map_or(f64::NAN, f64::log10);
        let field = Field::with_constant_output(
            &settings.config(outputs.len()),
            domain,
            settings.seed,
            &value,
        )?;
        Ok(Self {
            field,
            outputs,
            points,
            log10_e_centre,
            parts: None,
        })
    }

    /// Per-particle `E` and `ν`: the field's where it outputs them, else `values`'.
    ///
    /// # Errors
    /// A non-finite output, named.
    pub fn moduli(&self, values: &MaterialValues) -> Result<Moduli, FieldError> {
        self.moduli_at(&self.points, values)
    }

    /// Per-particle `E` and `ν` at other rest positions `points` (m), e.g. the particles of
    /// the same object on another grid: the field is a function of space, not of particles.
    /// With [`Parts`], each point takes its part's E.
    ///
    /// # Errors
    /// A non-finite output, named.
    pub fn moduli_at(
        &self,
        points: &[[f64; 3]],
        values: &MaterialValues,
    ) -> Result<Moduli, FieldError> {
        let mut m = self.field_moduli_at(points, values)?;
        if let Some(parts) = &self.parts {
            let part = parts.assign(&m.e);
            parts.apply(&part, &mut m);
        }
        Ok(m)
    }

    /// Per-particle `E` and `ν` at `points` from the field alone (without its parts).
    ///
    /// # Errors
    /// A non-finite output, named.
    pub fn field_moduli_at(
        &self,
        points: &[[f64; 3]],
        values: &MaterialValues,
    ) -> Result<Moduli, FieldError> {
        let y = self.field.forward(points)?;
        let k = self.outputs.len();
        let n = points.len();
        let mut m = Moduli {
            e: vec![values.get(Param::E).unwrap_or(f64::NAN); n],
            nu: vec![values.get(Param::Nu).unwrap_or(f64::NAN); n],
        };
        for (j, p) in self.outputs.iter().enumerate() {
            let target = if *p == Param::E { &mut m.e } else { &mut m.nu };
            for (i, t) in target.iter_mut().enumerate() {
                *t = decode(*p, y[i * k + j], self.log10_e_centre);
            }
        }
        Ok(m)
    }

    /// `∂L/∂output` per particle (point-major) from the per-particle `grad` at `moduli`.
    pub fn output_gradient(&self, moduli: &Moduli, grad: &Moduli) -> Vec<f64> {
        let k = self.outputs.len();
        let mut d = vec![0.0; self.points.len() * k];
        for (j, p) in self.outputs.iter().enumerate() {
            for i in 0..self.points.len() {
                d[i * k + j] = match p {
                    Param::E => {
                        let s = (moduli.e[i].log10() - self.log10_e_centre) / E_RANGE_DECADES;
                        grad.e[i] * moduli.e[i] * std::f64::consts::LN_10 * (1.0 - s * s)
                    }
                    _ => grad.nu[i] * p.dvalue_du(p.encode(moduli.nu[i])),
                };
            }
        }
        d
    }
}

/// The largest side (m) of the box around `points` (0 for none).
pub fn largest_extent(points: &[[f64; 3]]) -> f64 {
    let (lo, hi) = points.iter().fold(
        ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
        |(mut lo, mut hi), p| {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
            (lo, hi)
        },
    );
    (0..3).map(|a| hi[a] - lo[a]).fold(0.0f64, f64::max)
}

/// The 5th, 50th and 95th percentiles of `v` (NaN-free input; nearest rank).
pub fn percentiles(v: &[f64]) -> [f64; 3] {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let at = |q: f64| s[((s.len() - 1) as f64 * q).round() as usize];
    if s.is_empty() {
        return [f64::NAN; 3];
    }
    [at(0.05), at(0.5), at(0.95)]
}

/// The colour of `log10 E` on the map from `lo` (blue) through green to `hi` (red), RGB in
/// [0, 1] (a linear ramp; the legend in `material.json` names the two ends).
pub fn colour_of(log10_e: f64, lo: f64, hi: f64) -> [f64; 3] {
    let t = if hi > lo {
        ((log10_e - lo) / (hi - lo)).clamp(0.0, 1.0)
    } else {
        0.5
    };
    if t < 0.5 {
        let s = t * 2.0;
        [0.0, s, 1.0 - s]
    } else {
        let s = (t - 0.5) * 2.0;
        [s, 1.0 - s, 0.0]
    }
}

/// The field's weights as a long table (`field.material.arrow`): one row per number, with its
/// tensor's name and shape; the configuration, the box and what the outputs are in the schema
/// metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldTable {
    /// The weights.
    pub weights: FieldWeights,
    /// What the outputs hold, in output order: `E` (as `log10 E`) and/or `nu` (encoded) for a
    /// material field, `vx vy vz` (m/s) for a velocity field.
    pub outputs: Vec<String>,
    /// A material field's centre of E's bounded map ([`E_RANGE_DECADES`]).
    pub log10_e_centre: Option<f64>,
    /// A material field's parts ([`Parts`]), when kept.
    pub parts: Option<Parts>,
}

impl Table for FieldTable {
    const NAME: &'static str = "field_weights";
    const VERSION: u32 = 2;

    fn schema() -> Schema {
        Schema::new(vec![
            ArrowField::new("tensor", DataType::Utf8, false),
            ArrowField::new("shape", DataType::Utf8, false),
            ArrowField::new("index", DataType::UInt32, false),
            ArrowField::new("value", DataType::Float64, false),
        ])
        .with_metadata([("schema_version".to_string(), Self::VERSION.to_string())])
    }

    fn to_batch(&self) -> RecordBatch {
        let (mut name, mut shape, mut index, mut value) = (vec![], vec![], vec![], vec![]);
        for t in &self.weights.tensors {
            let s = t
                .shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join("x");
            for (i, v) in t.values.iter().enumerate() {
                name.push(t.name.clone());
                shape.push(s.clone());
                index.push(i as u32);
                value.push(*v);
            }
        }
        let meta = serde_json::json!({
            "config": self.weights.config,
            "domain_min": self.weights.domain_min,
            "domain_max": self.weights.domain_max,
            "outputs": self.outputs,
            "log10_e_centre": self.log10_e_centre,
            "parts": self.parts,
        });
        let schema = Self::schema();
        let mut md = schema.metadata().clone();
        md.insert("field".to_string(), meta.to_string());
        RecordBatch::try_new(
            Arc::new(schema.with_metadata(md)),
            vec![
                Arc::new(StringArray::from(name)),
                Arc::new(StringArray::from(shape)),
                Arc::new(UInt32Array::from(index)),
                Arc::new(Float64Array::from(value)),
            ],
        )
        .expect("columns match the schema")
    }

    fn from_batch(b: &RecordBatch, path: &Path) -> Result<Self, TableError> {
        let bad = |m: String| TableError::Invalid {
            path: path.to_path_buf(),
            message: m,
        };
        let meta: serde_json::Value = b
            .schema()
            .metadata()
            .get("field")
            .ok_or_else(|| bad("no `field` metadata (configuration and box)".into()))
            .and_then(|s| {
                serde_json::from_str(s).map_err(|e| bad(format!("`field` metadata: {e}")))
            })?;
        let config: pipe_field::FieldConfig = serde_json::from_value(meta["config"].clone())
            .map_err(|e| bad(format!("`field` metadata `config`: {e}")))?;
        let outputs: Vec<String> = serde_json::from_value(meta["outputs"].clone())
            .map_err(|e| bad(format!("`field` metadata `outputs`: {e}")))?;
        if outputs.len() != config.outputs {
            return Err(bad(format!(
                "`field` metadata `outputs` names {} outputs ({outputs:?}) for a field of {}",
                outputs.len(),
                config.outputs
            )));
        }
        let corner = |k: &str| -> Result<[f64; 3], TableError> {
            serde_json::from_value(meta[k].clone())
                .map_err(|e| bad(format!("`field` metadata `{k}`: {e}")))
        };
        let names = column::<StringArray>(b, "tensor");
        let shapes = column::<StringArray>(b, "shape");
        let values = column::<Float64Array>(b, "value");
        let mut tensors: Vec<pipe_field::weights::NamedTensor> = Vec::new();
        for i in 0..b.num_rows() {
            let name = names.value(i);
            if tensors.last().is_none_or(|t| t.name != name) {
                let shape = shapes
                    .value(i)
                    .split('x')
                    .map(|d| d.parse::<usize>())
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| bad(format!("row {i}: shape `{}`: {e}", shapes.value(i))))?;
                tensors.push(pipe_field::weights::NamedTensor {
                    name: name.to_string(),
                    shape,
                    values: Vec::new(),
                });
            }
            if let Some(t) = tensors.last_mut() {
                t.values.push(values.value(i));
            }
        }
        Ok(Self {
            weights: FieldWeights {
                config,
                domain_min: corner("domain_min")?,
                domain_max: corner("domain_max")?,
                tensors,
            },
            outputs,
            log10_e_centre: meta["log10_e_centre"].as_f64(),
            parts: match meta.get("parts") {
                None | Some(serde_json::Value::Null) => None,
                Some(v) => Some(
                    serde_json::from_value::<Parts>(v.clone())
                        .map_err(|e| bad(format!("`field` metadata `parts`: {e}")))?,
                ),
            },
        })
    }
}

/// Writes the field's weights to `path` (atomically, as every table).
pub fn write_weights(path: &Path, field: &MaterialField) -> Result<(), TableError> {
    table::write(
        path,
        &FieldTable {
            weights: field.field.weights(),
            outputs: field.outputs.iter().map(|q| q.name().to_string()).collect(),
            log10_e_centre: Some(field.log10_e_centre).filter(|c| c.is_finite()),
            parts: field.parts.clone(),
        },
    )
}

/// A field written with [`FieldTable`], and its outputs' names.
///
/// # Errors
/// An unreadable or inconsistent table, named with the path.
pub fn read_field(path: &Path) -> Result<(Field, FieldTable), String> {
    let t: FieldTable = table::read(path).map_err(|e| e.to_string())?;
    let field = Field::from_weights(&t.weights).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((field, t))
}

/// Per-particle `E` and `ν` at rest positions `points` (m) from the field written at `path`
/// (`field.material.arrow`), `values` for what it does not output. The field is a function
/// of space, so any particle set of the same object (another stage's, another grid) can ask
/// it; points outside its box take the value at the box's nearest face.
///
/// # Errors
/// An unreadable or inconsistent table, or a non-finite output, named with the path.
pub fn read_moduli(
    path: &Path,
    points: Vec<[f64; 3]>,
    values: &MaterialValues,
) -> Result<Moduli, String> {
    let (field, table) = read_field(path)?;
    let outputs = table
        .outputs
        .iter()
        .map(|n| match Param::from_name(n) {
            Some(q @ (Param::E | Param::Nu)) => Ok(q),
            _ => Err(format!(
                "{}: output `{n}` is not a material field's (E, nu)",
                path.display()
            )),
        })
        .collect::<Result<Vec<_>, _>>()?;
    let log10_e_centre = match (outputs.contains(&Param::E), table.log10_e_centre) {
        (true, Some(c)) => c,
        (true, None) => {
            return Err(format!(
                "{}: a field of E without `log10_e_centre` in its metadata",
                path.display()
            ));
        }
        (false, _) => f64::NAN,
    };
    if let Some(parts) = &table.parts
        && (parts.thresholds.len() + 1 != parts.len()
            || parts.is_empty()
            || !outputs.contains(&Param::E)
            || parts
                .log10_e
                .iter()
                .chain(&parts.thresholds)
                .any(|v| !v.is_finite()))
    {
        return Err(format!(
            "{}: `parts` needs one threshold fewer than parts, finite values and a field of E (found {} thresholds, {} parts)",
            path.display(),
            parts.thresholds.len(),
            parts.len()
        ));
    }
    MaterialField {
        field,
        outputs,
        points,
        log10_e_centre,
        parts: table.parts.clone(),
    }
    .moduli(values)
    .map_err(|e| format!("{}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::spec::MaterialFamily;

    fn field_over_a_bar() -> (MaterialField, MaterialValues) {
        let points: Vec<[f64; 3]> = (0..40)
            .map(|i| {
                [
                    f64::from(i) * 0.01,
                    0.05 * f64::from(i % 3),
                    0.02 * f64::from(i % 2),
                ]
            })
            .collect();
        let mut values =
            MaterialValues::guess(MaterialFamily::Elastic, 1000.0, &Default::default());
        values.values.insert(Param::E, 1e5);
        let mut f =
            MaterialField::starting_at(&FieldSettings::default(), points, vec![Param::E], &values)
                .unwrap();
        // Perturb the weights so the field varies over the points.
        let w: Vec<f64> = f
            .field
            .to_flat()
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.05 * ((i as f64) * 0.37).sin())
            .collect();
        f.field.set_flat(&w).unwrap();
        (f, values)
    }

    #[test]
    fn a_field_with_parts_round_trips_and_gives_each_point_its_parts_e() {
        let (mut f, values) = field_over_a_bar();
        let raw = f.moduli(&values).unwrap();
        let log_e: Vec<f64> = raw.e.iter().map(|e| e.log10()).collect();
        let lo = log_e.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = log_e.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert!(hi - lo > 1e-3, "the field varies: {lo} .. {hi}");
        let cut = 0.5 * (lo + hi);
        f.parts = Some(Parts {
            thresholds: vec![cut],
            log10_e: vec![4.0, 6.0],
        });
        let with = f.moduli(&values).unwrap();
        for (l, e) in log_e.iter().zip(&with.e) {
            assert_eq!(*e, if *l >= cut { 1e6 } else { 1e4 });
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("field.material.arrow");
        write_weights(&path, &f).unwrap();
        let read = read_moduli(&path, f.points.clone(), &values).unwrap();
        assert_eq!(read.e, with.e);
        // A table whose parts do not fit together is refused by name.
        f.parts = Some(Parts {
            thresholds: vec![cut, cut + 0.1],
            log10_e: vec![4.0, 6.0],
        });
        write_weights(&path, &f).unwrap();
        let err = read_moduli(&path, f.points.clone(), &values).unwrap_err();
        assert!(
            err.contains("`parts` needs one threshold fewer than parts"),
            "{err}"
        );
    }
}
