//! YAML text → JSON value tree plus a table of source positions.
//!
//! The pipeline file is parsed once with `saphyr` (position-annotated nodes), converted to a
//! `serde_json::Value` that typed stage parameters are deserialised from, and every node's
//! position is recorded under its dotted path (`stages.material.grid`, `scene.test_views[0]`) so
//! a later validation error can point at a line and column.

use std::collections::HashMap;

use saphyr::{LoadableYamlNode, MarkedYaml, Scalar, YamlData};
use serde_json::{Map, Number, Value};

/// 1-based line and column of a node in the pipeline file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Position {
    /// Line, 1-based.
    pub line: usize,
    /// Column, 1-based.
    pub col: usize,
}

impl std::fmt::Display for Position {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.line, self.col)
    }
}

/// Where each node sits: value positions and, for mapping entries, the key's position.
#[derive(Debug, Default, Clone)]
pub struct Positions {
    values: HashMap<String, Position>,
    keys: HashMap<String, Position>,
}

impl Positions {
    /// Position of the value at `path` (falls back to its key, then to the nearest parent's key).
    pub fn value(&self, path: &str) -> Option<Position> {
        if let Some(pos) = self.values.get(path) {
            return Some(*pos);
        }
        let mut p = path.to_string();
        loop {
            if let Some(pos) = self.keys.get(&p).or_else(|| self.values.get(&p)) {
                return Some(*pos);
            }
            match parent_path(&p) {
                Some(parent) => p = parent,
                None => return None,
            }
        }
    }

    /// Position of the key of the mapping entry at `path` (falls back to [`Self::value`]).
    pub fn key(&self, path: &str) -> Option<Position> {
        self.keys.get(path).copied().or_else(|| self.value(path))
    }
}

fn parent_path(path: &str) -> Option<String> {
    let cut = path.rfind(['.', '['])?;
    Some(path[..cut].to_string())
}

/// Join a mapping key onto a dotted path.
pub fn join(path: &str, key: &str) -> String {
    if path.is_empty() {
        key.to_string()
    } else {
        format!("{path}.{key}")
    }
}

/// A YAML syntax or structure problem, before any schema is applied.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct YamlError {
    /// Where it happened, if known.
    pub position: Option<Position>,
    /// What is wrong.
    pub message: String,
}

/// Parse one YAML document into a JSON value and the positions of its nodes.
pub fn parse(text: &str) -> Result<(Value, Positions), YamlError> {
    let docs = MarkedYaml::load_from_str(text).map_err(|e| YamlError {
        position: Some(Position {
            line: e.marker().line(),
            col: e.marker().col() + 1,
        }),
        message: e.info().to_string(),
    })?;
    let mut positions = Positions::default();
    match docs.len() {
        0 => Ok((Value::Null, positions)),
        1 => {
            let value = convert(&docs[0], "", &mut positions)?;
            Ok((value, positions))
        }
        _ => Err(YamlError {
            position: Some(pos_of(&docs[1])),
            message: "the file holds more than one YAML document (`---`); a pipeline is one".into(),
        }),
    }
}

/// Parse a single YAML value given on the command line (`--set stage.key=VALUE`).
pub fn parse_value(text: &str) -> Result<Value, YamlError> {
    let (v, _) = parse(text)?;
    Ok(v)
}

fn pos_of(node: &MarkedYaml<'_>) -> Position {
    Position {
        line: node.span.start.line(),
        col: node.span.start.col() + 1,
    }
}

fn convert(
    node: &MarkedYaml<'_>,
    path: &str,
    positions: &mut Positions,
) -> Result<Value, YamlError> {
    positions.values.insert(path.to_string(), pos_of(node));
    let err = |message: String| YamlError {
        position: Some(pos_of(node)),
        message,
    };
    Ok(match &node.data {
        YamlData::Value(s) => scalar(s).map_err(err)?,
        YamlData::Representation(text, _, _) => Value::String(text.to_string()),
        YamlData::Sequence(items) => {
            let mut out = Vec::with_capacity(items.len());
            for (i, item) in items.iter().enumerate() {
                out.push(convert(item, &format!("{path}[{i}]"), positions)?);
            }
            Value::Array(out)
        }
        YamlData::Mapping(map) => {
            let mut out = Map::new();
            for (k, v) in map.iter() {
                let key = match &k.data {
                    YamlData::Value(Scalar::String(s)) => s.to_string(),
                    YamlData::Value(Scalar::Integer(i)) => i.to_string(),
                    YamlData::Value(Scalar::Boolean(b)) => b.to_string(),
                    _ => {
                        return Err(YamlError {
                            position: Some(pos_of(k)),
                            message: "mapping keys must be plain words".into(),
                        });
                    }
                };
                let child = join(path, &key);
                positions.keys.insert(child.clone(), pos_of(k));
                let value = convert(v, &child, positions)?;
                out.insert(key, value);
            }
            Value::Object(out)
        }
        YamlData::Tagged(_, inner) => convert(inner, path, positions)?,
        YamlData::Alias(_) => return Err(err("YAML aliases (`*name`) are not supported".into())),
        YamlData::BadValue => return Err(err("unreadable value".into())),
    })
}

fn scalar(s: &Scalar<'_>) -> Result<Value, String> {
    Ok(match s {
        Scalar::Null => Value::Null,
        Scalar::Boolean(b) => Value::Bool(*b),
        Scalar::Integer(i) => Value::Number((*i).into()),
        Scalar::FloatingPoint(f) => {
            let f = f.into_inner();
            Value::Number(
                Number::from_f64(f)
                    .ok_or_else(|| format!("non-finite number {f} is not allowed"))?,
            )
        }
        Scalar::String(s) => Value::String(s.to_string()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_positions_of_nested_keys() {
        let text = "name: x\nstages:\n  material:\n    grid: 64\n    learn: [E, nu]\n";
        let (v, pos) = parse(text).unwrap();
        assert_eq!(v["stages"]["material"]["grid"], 64);
        assert_eq!(
            pos.key("stages.material.grid"),
            Some(Position { line: 4, col: 5 })
        );
        assert_eq!(pos.value("stages.material.learn[1]").unwrap().line, 5);
        // Unknown deeper paths fall back to the nearest known parent.
        assert_eq!(pos.value("stages.material.nope").unwrap().line, 3);
    }

    #[test]
    fn syntax_errors_carry_a_position() {
        let e = parse("a: [1, 2\nb: 3\n").unwrap_err();
        assert!(e.position.is_some(), "{e:?}");
    }

    #[test]
    fn duplicate_keys_are_rejected() {
        let e = parse("a: 1\na: 2\n").unwrap_err();
        assert!(e.message.contains("duplicate"), "{e:?}");
        assert_eq!(e.position.unwrap().line, 2);
    }

    #[test]
    fn non_finite_floats_are_rejected() {
        assert!(parse("a: .nan\n").is_err());
    }
}
