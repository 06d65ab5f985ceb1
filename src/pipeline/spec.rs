//! The pipeline file: YAML → typed [`Pipeline`], with presets and `--set` overrides.
//!
//! Resolution order for a stage's parameters (later wins): the stage's own defaults, the
//! preset's values, the file's values, `--set stage.key=value`. Every error names the file,
//! the line and column, the bad key or value and, for unknown keys, the nearest valid one.

use std::path::{Path, PathBuf};

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::stage::{ParamError, Registry, Stage};
use super::yaml::{self, Position, Positions};

/// A named bundle of stage defaults trading speed for accuracy (ARCHITECTURE §9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Seconds to minutes on 2 cores: small images, few particles, coarse grid.
    Draft,
    /// The default balance.
    #[default]
    Standard,
    /// The paper's settings.
    Paper,
}

impl Preset {
    /// Parse `draft | standard | paper`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "draft" => Some(Self::Draft),
            "standard" => Some(Self::Standard),
            "paper" => Some(Self::Paper),
            _ => None,
        }
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Draft => "draft",
            Self::Standard => "standard",
            Self::Paper => "paper",
        }
    }
}

/// Layout of the dataset folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum DatasetKind {
    /// PAC-NeRF: `all_data.json` + `data/r_<cam>_<frame>.png` (ARCHITECTURE §6).
    Pacnerf,
    /// PhysDreamer: a trained 3DGS `point_cloud.ply`, the points selecting the object and its
    /// moving part, `transforms_train.json` (or COLMAP `sparse/0`) and a PNG video per camera
    /// (`crate::io::physdreamer`).
    Physdreamer,
}

impl DatasetKind {
    /// The name in `scene.dataset`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Pacnerf => "pacnerf",
            Self::Physdreamer => "physdreamer",
        }
    }
}

/// The object's material family; picks the one constitutive model that runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MaterialFamily {
    /// Compressible neo-Hookean (PAC-NeRF).
    Elastic,
    /// Fixed-corotated elasticity (PhysGaussian / PhysDreamer).
    ElasticFcr,
    /// Hencky + von Mises, no viscosity.
    Plasticine,
    /// Hencky + von Mises with viscosity.
    NonNewtonian,
    /// J-based pressure + viscosity.
    Newtonian,
    /// Hencky + Drucker–Prager.
    Sand,
}

/// The `scene:` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// Dataset layout.
    pub dataset: DatasetKind,
    /// Dataset folder; relative paths are relative to the pipeline file's folder.
    pub path: PathBuf,
    /// Camera indices held out of training and scored in `evaluate`.
    #[serde(default)]
    pub test_views: Vec<u16>,
    /// Material family of the simulated object.
    #[serde(default)]
    pub material: Option<MaterialFamily>,
    /// Density of the object (kg/m³); PAC-NeRF assumes 1000.
    #[serde(default = "default_density")]
    pub density: f64,
    /// Gravity (m/s²).
    #[serde(default = "default_gravity")]
    pub gravity: [f64; 3],
    /// What acts on the object besides gravity, in the simulation file's syntax (`pipe
    /// simulate`); default: a sticky ground at `y = 0`, as in every PAC-NeRF scene. An empty
    /// list leaves the object in free fall.
    #[serde(default = "default_boundaries")]
    pub boundaries: Vec<BoundaryItem>,
    /// The MPM substeps per frame the physics stages take whenever a fixed count may (CFL
    /// number ≤ 0.5 and the viscous limit; otherwise the automatic count, CFL 0.3). For a
    /// synthetic capture: the step of the simulator that made it. MPM's results depend on the
    /// step (each transfer damps a little; a von Mises blob re-simulated with its true
    /// parameters at 100 and 400 substeps a frame ends 2.5 mm lower and 3.0 mm higher than at
    /// its maker's 200), and a learner left to its own step explains the difference with a
    /// wrong material. PAC-NeRF's configs use 200 a frame at 24 frames a second (`dt = 1/4800`
    /// s). Unset: the automatic count alone (a real capture).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 1, max = 100000))]
    pub prefer_substeps: Option<u32>,
}

impl SceneSpec {
    /// The physical settings a simulating stage's cache key holds (`material`, `density`,
    /// `gravity`, `boundaries`, and `prefer_substeps` when set, so that entries made before it
    /// existed keep their keys).
    pub fn physics_key(&self) -> serde_json::Value {
        let mut key = serde_json::json!({
            "material": self.material,
            "density": self.density,
            "gravity": self.gravity,
            "boundaries": self.boundaries,
        });
        if let Some(n) = self.prefer_substeps {
            key["prefer_substeps"] = n.into();
        }
        key
    }
}

fn default_density() -> f64 {
    1000.0
}

fn default_gravity() -> [f64; 3] {
    [0.0, -9.8, 0.0]
}

fn default_boundaries() -> Vec<BoundaryItem> {
    vec![BoundaryItem::Ground {
        y: 0.0,
        condition: BoundaryCondition::Sticky,
    }]
}

/// How a boundary treats the grid velocities it acts on.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum BoundaryCondition {
    /// Velocity set to zero.
    #[default]
    Sticky,
    /// Normal component removed, tangential kept.
    Slip,
    /// Normal component removed only when moving into the obstacle.
    Separate,
}

/// One item of `scene.boundaries` (the simulation file's `boundaries:` syntax).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum BoundaryItem {
    /// The plane `y = y` (m), free side above.
    Ground {
        /// Height (m).
        #[serde(default)]
        y: f64,
        /// Treatment.
        #[serde(default)]
        condition: BoundaryCondition,
    },
    /// The plane through `point` (m) with `normal` pointing into the free side.
    HalfSpace {
        /// A point on the plane (m).
        point: [f64; 3],
        /// Normal (into the free side).
        normal: [f64; 3],
        /// Treatment.
        #[serde(default)]
        condition: BoundaryCondition,
    },
    /// A solid box obstacle (m).
    Box {
        /// Lower corner (m).
        min: [f64; 3],
        /// Upper corner (m).
        max: [f64; 3],
        /// Treatment.
        #[serde(default)]
        condition: BoundaryCondition,
    },
}

/// One stage as resolved from the file.
#[derive(Debug, Clone, PartialEq)]
pub struct StageSpec {
    /// Name in the file: the kind, or `<kind>.<instance>` for each named instance of a kind
    /// that takes a map of them (`edit: {press: {...}}` gives the stage `edit.press`).
    pub name: String,
    /// Stage kind (the registry's key).
    pub kind: String,
    /// Explicit upstream stages (`needs:`), if the file gives them.
    pub needs: Option<Vec<String>>,
    /// Resolved parameters (defaults ⊕ preset ⊕ file ⊕ `--set`), canonical.
    pub params: Value,
    /// Line of the stage's key in the file, for messages.
    pub position: Option<Position>,
}

/// A loaded, validated pipeline file.
#[derive(Debug, Clone, PartialEq)]
pub struct Pipeline {
    /// The file it came from.
    pub file: PathBuf,
    /// `name:`.
    pub name: String,
    /// Effective preset (file's, or `--preset`).
    pub preset: Preset,
    /// `scene:`, with `path` made absolute.
    pub scene: SceneSpec,
    /// Stages in file order.
    pub stages: Vec<StageSpec>,
    /// `sweep:`: the axes `pipe sweep` varies when the command line gives no `--over` for
    /// them, in file order (`pipe run` ignores them).
    pub sweep: Vec<crate::sweep::Axis>,
}

impl Pipeline {
    /// The stage named `name`.
    pub fn stage(&self, name: &str) -> Option<&StageSpec> {
        self.stages.iter().find(|s| s.name == name)
    }
}

/// Command-line changes applied on top of the file.
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    /// `--preset`.
    pub preset: Option<Preset>,
    /// `--set stage.key=value`, in order.
    pub sets: Vec<String>,
}

/// A problem in the pipeline file or its overrides.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{file}: {message}{}{}", position.map(|p| format!(" at line {p}")).unwrap_or_default(), hint.as_ref().map(|h| format!("; {h}")).unwrap_or_default())]
pub struct SpecError {
    /// The pipeline file.
    pub file: String,
    /// Line and column, when the problem is in the file.
    pub position: Option<Position>,
    /// What is wrong.
    pub message: String,
    /// A suggestion (`did you mean ...?`).
    pub hint: Option<String>,
}

const TOP_KEYS: [&str; 5] = ["name", "scene", "preset", "stages", "sweep"];

/// Read, validate and resolve a pipeline file.
pub fn load(
    path: &Path,
    registry: &Registry,
    overrides: &Overrides,
) -> Result<Pipeline, SpecError> {
    let text = std::fs::read_to_string(path).map_err(|e| SpecError {
        file: path.display().to_string(),
        position: None,
        message: format!("cannot read the pipeline file: {e}"),
        hint: None,
    })?;
    parse(path, &text, registry, overrides)
}

/// Validate and resolve pipeline text (`path` names it in messages and anchors relative paths).
pub fn parse(
    path: &Path,
    text: &str,
    registry: &Registry,
    overrides: &Overrides,
) -> Result<Pipeline, SpecError> {
    let ctx = Ctx {
        file: path.display().to_string(),
        positions: Positions::default(),
    };
    let (root, positions) = yaml::parse(text).map_err(|e| ctx.err(e.position, e.message, None))?;
    let ctx = Ctx { positions, ..ctx };
    let Value::Object(mut root) = root else {
        return Err(ctx.err(
            Some(Position { line: 1, col: 1 }),
            "a pipeline file is a mapping with `name`, `scene`, `stages` (and optionally `preset`)"
                .into(),
            None,
        ));
    };
    for key in root.keys() {
        if !TOP_KEYS.contains(&key.as_str()) {
            return Err(ctx.unknown_key(key, "", &TOP_KEYS.map(String::from)));
        }
    }
    let name = match root.remove("name") {
        Some(Value::String(s)) if !s.trim().is_empty() => s,
        Some(other) => {
            return Err(ctx.at(
                "name",
                format!("`name` must be a non-empty string, found {other}"),
            ));
        }
        None => return Err(ctx.missing("name", "")),
    };
    let preset = match (overrides.preset, root.remove("preset")) {
        (Some(p), _) => p,
        (None, None) => Preset::default(),
        (None, Some(v)) => v.as_str().and_then(Preset::parse).ok_or_else(|| {
            ctx.at(
                "preset",
                format!("unknown preset {v}; expected one of draft, standard, paper"),
            )
        })?,
    };

    let sweep = match root.remove("sweep") {
        None => Vec::new(),
        Some(v) => sweep_axes(&ctx, v)?,
    };

    let mut sets = parse_sets(&ctx, &overrides.sets)?;

    let mut scene_value = root
        .remove("scene")
        .ok_or_else(|| ctx.missing("scene", ""))?;
    for s in sets.iter_mut().filter(|s| s.stage == "scene") {
        set_path(&mut scene_value, &s.key_path, s.value.clone());
    }
    let mut scene: SceneSpec = serde_path_to_error::deserialize(&scene_value).map_err(|e| {
        let pe = ParamError {
            path: e.path().to_string().trim_start_matches('.').to_string(),
            message: e.inner().to_string(),
        };
        let sets: Vec<&SetOverride> = sets.iter().collect();
        ctx.param_error("scene", &pe, &scene_keys(), &sets)
    })?;
    // A relative `path` in the file is relative to the file's folder; one given on the
    // command line (`--set scene.path=…`) is relative to the current directory, like any
    // other path typed there.
    let path_from_cli = sets
        .iter()
        .any(|s| s.stage == "scene" && s.key_path.first().is_some_and(|k| k == "path"));
    if scene.path.is_relative() && !path_from_cli {
        let base = path.parent().unwrap_or(Path::new("."));
        scene.path = base.join(&scene.path);
    }

    let stages_value = root
        .remove("stages")
        .ok_or_else(|| ctx.missing("stages", ""))?;
    let stages_map = match stages_value {
        Value::Object(m) if !m.is_empty() => m,
        _ => {
            return Err(ctx.at(
                "stages",
                "`stages` must be a non-empty mapping of stage name to parameters".into(),
            ));
        }
    };
    let kinds: Vec<String> = registry.kinds().iter().map(|s| s.to_string()).collect();
    for s in &sets {
        if s.stage != "scene" && !stages_map.contains_key(&s.stage) {
            return Err(SpecError {
                file: ctx.file.clone(),
                position: None,
                message: format!("--set {}: the pipeline has no stage `{}`", s.raw, s.stage),
                hint: suggest(&s.stage, stages_map.keys()).map(|k| format!("did you mean `{k}`?")),
            });
        }
    }

    let mut stages = Vec::new();
    for (stage_name, entry) in stages_map {
        let stage_path = format!("stages.{stage_name}");
        let Some(stage) = registry.get(&stage_name) else {
            return Err(ctx.unknown_stage(&stage_name, &kinds));
        };
        if !stage.named_instances() {
            let sets: Vec<&SetOverride> = sets.iter().filter(|s| s.stage == stage_name).collect();
            stages.push(resolve_stage(
                &ctx,
                stage.as_ref(),
                (&stage_name, &stage_path),
                entry,
                preset,
                (&sets, &sets),
            )?);
            continue;
        }
        // A map of named instances, each its own stage `<kind>.<name>` (its own cache entry).
        // `--set edit.press.frames=20` sets `frames` of instance `press`.
        let mut whole = entry;
        for s in sets.iter().filter(|s| s.stage == stage_name) {
            // A key of an instance the file lacks is a slip (`--set edit.name={...}` adds one).
            let names: Vec<String> = whole
                .as_object()
                .map(|m| m.keys().cloned().collect())
                .unwrap_or_default();
            if s.key_path.len() > 1 && !names.contains(&s.key_path[0]) {
                return Err(SpecError {
                    file: ctx.file.clone(),
                    position: None,
                    message: format!(
                        "--set {}: the pipeline has no {stage_name} `{}` (it has {})",
                        s.raw,
                        s.key_path[0],
                        if names.is_empty() {
                            "none".to_string()
                        } else {
                            names.join(", ")
                        }
                    ),
                    hint: suggest(&s.key_path[0], &names).map(|k| format!("did you mean `{k}`?")),
                });
            }
            set_path(&mut whole, &s.key_path, s.value.clone());
        }
        let instances = match whole {
            Value::Object(m) if !m.is_empty() => m,
            other => {
                return Err(ctx.at(
                    &stage_path,
                    format!(
                        "stage `{stage_name}` takes a mapping of names to parameters, one per \
                         {stage_name} (e.g. `{stage_name}: {{press: {{...}}}}`), found {}",
                        if other.is_null() {
                            "nothing".to_string()
                        } else {
                            other.to_string()
                        }
                    ),
                ));
            }
        };
        for (instance, entry) in instances {
            let path = format!("{stage_path}.{instance}");
            if instance.is_empty()
                || !instance
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            {
                return Err(ctx.err(
                    ctx.positions.key(&path),
                    format!(
                        "invalid name `{instance}` in {stage_path}: a name is made of letters, \
                         digits, `_` and `-` (it names the cache entry)"
                    ),
                    None,
                ));
            }
            let name = format!("{stage_name}.{instance}");
            let sets: Vec<&SetOverride> = sets
                .iter()
                .filter(|s| s.stage == stage_name && s.key_path.first() == Some(&instance))
                .collect();
            // The sets are in `entry` already; they only name themselves in messages.
            stages.push(resolve_stage(
                &ctx,
                stage.as_ref(),
                (&name, &path),
                entry,
                preset,
                (&[], &sets),
            )?);
        }
    }
    Ok(Pipeline {
        file: path.to_path_buf(),
        name,
        preset,
        scene,
        stages,
        sweep,
    })
}

/// One stage's entry resolved: `needs:` taken out, the preset's parameters under the file's,
/// `apply` (`--set` of this stage) on top, validated by the stage; an error caused by one of
/// `origin` says so. `name` and `stage_path` (`stages.<name>`, or `stages.<kind>.<instance>`)
/// name it.
fn resolve_stage(
    ctx: &Ctx,
    stage: &dyn Stage,
    (name, stage_path): (&str, &str),
    entry: Value,
    preset: Preset,
    (apply, origin): (&[&SetOverride], &[&SetOverride]),
) -> Result<StageSpec, SpecError> {
    let mut entry = match entry {
        Value::Null => Map::new(),
        Value::Object(m) => m,
        other => {
            return Err(ctx.at(
                stage_path,
                format!("stage `{name}` takes a mapping of parameters, found {other}"),
            ));
        }
    };
    let needs = match entry.remove("needs") {
        None => None,
        Some(Value::String(s)) => Some(vec![s]),
        Some(Value::Array(items)) => Some(
            items
                .into_iter()
                .map(|v| match v {
                    Value::String(s) => Ok(s),
                    other => Err(ctx.at(
                        &format!("{stage_path}.needs"),
                        format!("`needs` lists stage names, found {other}"),
                    )),
                })
                .collect::<Result<Vec<_>, _>>()?,
        ),
        Some(other) => {
            return Err(ctx.at(
                &format!("{stage_path}.needs"),
                format!("`needs` lists stage names, found {other}"),
            ));
        }
    };
    let mut merged = stage.preset_params(preset);
    deep_merge(&mut merged, Value::Object(entry));
    for s in apply {
        set_path(&mut merged, &s.key_path, s.value.clone());
    }
    let params = stage.resolve_params(&merged).map_err(|e| {
        let mut keys = schema_keys(&stage.params_schema());
        keys.push("needs".into());
        ctx.param_error(stage_path, &e, &keys, origin)
    })?;
    Ok(StageSpec {
        position: ctx.positions.key(stage_path),
        name: name.to_string(),
        kind: stage.kind().to_string(),
        needs,
        params,
    })
}

/// The `sweep:` block: a mapping from `preset` or `stage.key` to the list of its values, e.g.
/// `sweep: {material.cells: [12, 16, 24], preset: [draft, standard]}` (the first key varies
/// slowest, as the first `--over`).
fn sweep_axes(ctx: &Ctx, v: Value) -> Result<Vec<crate::sweep::Axis>, SpecError> {
    let Value::Object(map) = v else {
        return Err(ctx.at(
            "sweep",
            format!(
                "`sweep` must map `preset` or stage.key to a list of values, \
                 e.g. sweep: {{material.cells: [12, 16, 24]}}; found {v}"
            ),
        ));
    };
    let mut axes = Vec::new();
    for (key, values) in map {
        let Value::Array(values) = values else {
            return Err(ctx.at(
                &format!("sweep.{key}"),
                format!(
                    "`sweep.{key}` must be a list of values, e.g. [12, 16, 24]; found {values}"
                ),
            ));
        };
        if values.is_empty() {
            return Err(ctx.at(
                &format!("sweep.{key}"),
                format!("`sweep.{key}` lists no value"),
            ));
        }
        // Each value as `--set` takes it: plain scalars as written, anything with a comma,
        // bracket or quote as JSON (a YAML flow value).
        let text: Vec<String> = values
            .iter()
            .map(|v| match v {
                Value::String(s) if !s.contains([',', '[', ']', '{', '}', '"', '\'']) => s.clone(),
                other => other.to_string(),
            })
            .collect();
        let axis = crate::sweep::Axis::parse(&format!("{key}={}", text.join(",")))
            .map_err(|e| ctx.at(&format!("sweep.{key}"), format!("in `sweep:`: {e}")))?;
        axes.push(axis);
    }
    Ok(axes)
}

/// Property names of an object schema (for "did you mean").
pub fn schema_keys(schema: &schemars::Schema) -> Vec<String> {
    schema
        .get("properties")
        .and_then(|p| p.as_object())
        .map(|m| m.keys().cloned().collect())
        .unwrap_or_default()
}

fn scene_keys() -> Vec<String> {
    schema_keys(&schemars::schema_for!(SceneSpec))
}

/// The nearest candidate to `word`, if any is close enough to be a plausible typo.
pub fn suggest<'a>(
    word: &str,
    candidates: impl IntoIterator<Item = &'a String>,
) -> Option<&'a String> {
    candidates
        .into_iter()
        .map(|c| (strsim::damerau_levenshtein(word, c), c))
        .filter(|(d, c)| {
            *d <= (c.len().max(word.len()) / 3).max(1) || strsim::jaro_winkler(word, c) > 0.85
        })
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// `a` ⊕ `b`: objects merge key by key (recursively), anything else in `b` replaces `a`.
pub fn deep_merge(a: &mut Value, b: Value) {
    match (a, b) {
        (Value::Object(a), Value::Object(b)) => {
            for (k, v) in b {
                match a.get_mut(&k) {
                    Some(slot) => deep_merge(slot, v),
                    None => {
                        a.insert(k, v);
                    }
                }
            }
        }
        (slot, b) => *slot = b,
    }
}

fn set_path(target: &mut Value, key_path: &[String], value: Value) {
    let mut cur = target;
    for k in key_path {
        if !cur.is_object() {
            *cur = Value::Object(Map::new());
        }
        let Value::Object(m) = cur else {
            unreachable!()
        };
        cur = m.entry(k.clone()).or_insert(Value::Null);
    }
    *cur = value;
}

#[derive(Debug)]
struct SetOverride {
    raw: String,
    stage: String,
    key_path: Vec<String>,
    value: Value,
}

fn parse_sets(ctx: &Ctx, sets: &[String]) -> Result<Vec<SetOverride>, SpecError> {
    sets.iter()
        .map(|raw| {
            let bad = |message: String| SpecError {
                file: ctx.file.clone(),
                position: None,
                message,
                hint: Some("write it as --set stage.key=value, e.g. --set material.grid=48".into()),
            };
            let (lhs, rhs) = raw
                .split_once('=')
                .ok_or_else(|| bad(format!("--set {raw}: missing `=`")))?;
            let mut parts = lhs.trim().split('.').map(str::to_string);
            let stage = parts.next().unwrap_or_default();
            let key_path: Vec<String> = parts.collect();
            if stage.is_empty() || key_path.is_empty() || key_path.iter().any(String::is_empty) {
                return Err(bad(format!("--set {raw}: the key must be stage.key")));
            }
            let value = yaml::parse_value(rhs).map_err(|e| {
                bad(format!(
                    "--set {raw}: the value is not valid YAML: {}",
                    e.message
                ))
            })?;
            Ok(SetOverride {
                raw: raw.clone(),
                stage,
                key_path,
                value,
            })
        })
        .collect()
}

struct Ctx {
    file: String,
    positions: Positions,
}

impl Ctx {
    fn err(&self, position: Option<Position>, message: String, hint: Option<String>) -> SpecError {
        SpecError {
            file: self.file.clone(),
            position,
            message,
            hint,
        }
    }

    fn at(&self, path: &str, message: String) -> SpecError {
        self.err(self.positions.value(path), message, None)
    }

    fn missing(&self, key: &str, parent: &str) -> SpecError {
        let where_ = if parent.is_empty() {
            "at the top level".to_string()
        } else {
            format!("in {parent}")
        };
        self.err(
            self.positions
                .value(parent)
                .or(Some(Position { line: 1, col: 1 })),
            format!("missing key `{key}` {where_}"),
            None,
        )
    }

    fn unknown_key(&self, key: &str, parent: &str, valid: &[String]) -> SpecError {
        let full = yaml::join(parent, key);
        let where_ = if parent.is_empty() {
            "at the top level".to_string()
        } else {
            format!("in {parent}")
        };
        let hint = match suggest(key, valid) {
            Some(s) => format!("did you mean `{s}`?"),
            None => format!("valid keys: {}", valid.join(", ")),
        };
        self.err(
            self.positions.key(&full),
            format!("unknown key `{key}` {where_}"),
            Some(hint),
        )
    }

    fn unknown_stage(&self, name: &str, kinds: &[String]) -> SpecError {
        let hint = match suggest(name, kinds) {
            Some(s) => format!("did you mean `{s}`? (stages: {})", kinds.join(", ")),
            None => format!("known stages: {}", kinds.join(", ")),
        };
        self.err(
            self.positions.key(&format!("stages.{name}")),
            format!("unknown stage `{name}` in stages"),
            Some(hint),
        )
    }

    /// Turn a serde error inside `prefix` (`stages.material`, `scene`) into a located message.
    fn param_error(
        &self,
        prefix: &str,
        e: &ParamError,
        valid: &[String],
        sets: &[&SetOverride],
    ) -> SpecError {
        let full = if e.path.is_empty() {
            prefix.to_string()
        } else {
            format!("{prefix}.{}", e.path)
        };
        let origin = sets
            .iter()
            .find(|s| {
                let p = format!(
                    "{}.{}",
                    if s.stage == "scene" {
                        "scene".to_string()
                    } else {
                        format!("stages.{}", s.stage)
                    },
                    s.key_path.join(".")
                );
                full.starts_with(&p) || p.starts_with(&full)
            })
            .map(|s| format!(" (from --set {})", s.raw));
        if let Some(rest) = e.message.strip_prefix("unknown field `") {
            let key = rest.split('`').next().unwrap_or_default();
            let parent = full
                .strip_suffix(&format!(".{key}"))
                .map(str::to_string)
                .unwrap_or_else(|| full.clone());
            let mut err = self.unknown_key(key, &parent, valid);
            if let Some(o) = origin {
                err.message.push_str(&o);
                err.position = None;
            }
            return err;
        }
        if let Some(rest) = e.message.strip_prefix("missing field `") {
            let key = rest.split('`').next().unwrap_or_default();
            return self.missing(key, &full);
        }
        let message = format!(
            "{full}: {}{}",
            e.message,
            origin.clone().unwrap_or_default()
        );
        let position = if origin.is_some() {
            None
        } else {
            self.positions.value(&full)
        };
        self.err(position, message, None)
    }
}

/// The JSON Schema of the pipeline file, built from the registered stages.
pub fn json_schema(registry: &Registry) -> Value {
    let mut defs = Map::new();
    let mut take = |schema: schemars::Schema| -> Value {
        let mut v = schema.to_value();
        if let Value::Object(m) = &mut v {
            if let Some(Value::Object(d)) = m.remove("$defs") {
                defs.extend(d);
            }
            m.remove("$schema");
        }
        v
    };
    let scene = take(schemars::schema_for!(SceneSpec));
    let preset = take(schemars::schema_for!(Preset));
    let mut stage_props = Map::new();
    for stage in registry.iter() {
        let mut s = take(stage.params_schema());
        if let Value::Object(m) = &mut s {
            m.insert(
                "description".into(),
                Value::String(stage.description().into()),
            );
            let props = m
                .entry("properties")
                .or_insert_with(|| Value::Object(Map::new()));
            if let Value::Object(p) = props {
                p.insert(
                    "needs".into(),
                    serde_json::json!({
                        "description": "Upstream stages whose outputs this stage reads (default: the kind's standard upstream).",
                        "type": "array", "items": {"type": "string"}
                    }),
                );
            }
            m.insert("type".into(), serde_json::json!(["object", "null"]));
        }
        if stage.named_instances() {
            // A map of names to parameters, each name a stage of its own.
            let description = stage.description();
            if let Value::Object(m) = &mut s {
                m.remove("description");
            }
            s = serde_json::json!({
                "description": format!("{description}. A mapping of names to parameters: each name is a stage `{}.<name>` with its own cache entry.", stage.kind()),
                "type": "object",
                "minProperties": 1,
                "propertyNames": {"pattern": "^[A-Za-z0-9_-]+$"},
                "additionalProperties": s
            });
        }
        stage_props.insert(stage.kind().to_string(), s);
    }
    serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "pipe pipeline file",
        "type": "object",
        "additionalProperties": false,
        "required": ["name", "scene", "stages"],
        "properties": {
            "name": {"type": "string", "minLength": 1},
            "preset": preset,
            "scene": scene,
            "stages": {
                "type": "object",
                "minProperties": 1,
                "additionalProperties": false,
                "properties": stage_props
            },
            "sweep": {
                "description": "Axes `pipe sweep` varies (`pipe run` ignores them): `preset` or `stage.key` to the list of its values; the first key varies slowest. A `--over` of the same key replaces the file's axis.",
                "type": "object",
                "additionalProperties": {"type": "array", "minItems": 1}
            }
        },
        "$defs": defs
    })
}
