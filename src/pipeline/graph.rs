//! The stage DAG: edges, topological order, and `--from` / `--until` selection.

use std::collections::{BTreeMap, BTreeSet};

use super::spec::{Pipeline, SpecError, suggest};
use super::stage::Registry;

/// Stages with their upstream edges, in a topological order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Graph {
    /// Stage names, each after all of its upstreams (ties broken by file order).
    pub order: Vec<String>,
    /// Upstream stage names of each stage.
    pub upstream: BTreeMap<String, Vec<String>>,
}

impl Graph {
    /// Build the DAG: `needs:` if given, else the kind's standard upstream kinds that are present.
    pub fn build(pipeline: &Pipeline, registry: &Registry) -> Result<Self, SpecError> {
        let names: Vec<String> = pipeline.stages.iter().map(|s| s.name.clone()).collect();
        let err = |position, message: String, hint: Option<String>| SpecError {
            file: pipeline.file.display().to_string(),
            position,
            message,
            hint,
        };
        let mut upstream = BTreeMap::new();
        for s in &pipeline.stages {
            let ups: Vec<String> = match &s.needs {
                Some(needs) => {
                    for n in needs {
                        if !names.contains(n) {
                            return Err(err(
                                s.position,
                                format!(
                                    "stage `{}` needs `{n}`, which is not a stage of this pipeline",
                                    s.name
                                ),
                                suggest(n, &names).map(|k| format!("did you mean `{k}`?")),
                            ));
                        }
                        if n == &s.name {
                            return Err(err(
                                s.position,
                                format!("stage `{}` needs itself", s.name),
                                None,
                            ));
                        }
                    }
                    needs.clone()
                }
                None => registry
                    .get(&s.kind)
                    .map(|st| st.default_upstream())
                    .unwrap_or_default()
                    .iter()
                    .filter(|k| names.iter().any(|n| n == *k))
                    .map(|k| k.to_string())
                    .collect(),
            };
            upstream.insert(s.name.clone(), ups);
        }
        // Kahn's algorithm; among ready stages take the earliest in file order.
        let mut remaining: Vec<String> = names.clone();
        let mut order = Vec::new();
        while !remaining.is_empty() {
            let pick = remaining
                .iter()
                .position(|n| upstream[n].iter().all(|u| order.contains(u)));
            match pick {
                Some(i) => order.push(remaining.remove(i)),
                None => {
                    let cycle = find_cycle(&remaining, &upstream);
                    let first = pipeline.stage(&cycle[0]).and_then(|s| s.position);
                    return Err(err(
                        first,
                        format!("the stages form a cycle: {}", cycle.join(" -> ")),
                        Some("remove one of these `needs:` entries".into()),
                    ));
                }
            }
        }
        Ok(Self { order, upstream })
    }

    /// All stages that (transitively) read `name`'s outputs, plus `name` itself.
    pub fn descendants(&self, name: &str) -> BTreeSet<String> {
        let mut out = BTreeSet::from([name.to_string()]);
        for n in &self.order {
            if self.upstream[n].iter().any(|u| out.contains(u)) {
                out.insert(n.clone());
            }
        }
        out
    }

    /// `name` and everything it (transitively) reads.
    pub fn ancestors(&self, name: &str) -> BTreeSet<String> {
        let mut out = BTreeSet::from([name.to_string()]);
        for n in self.order.iter().rev() {
            if out.contains(n) {
                out.extend(self.upstream[n].iter().cloned());
            }
        }
        out
    }
}

/// A cycle among `remaining` (every one of them has an unmet upstream), first name repeated last.
fn find_cycle(remaining: &[String], upstream: &BTreeMap<String, Vec<String>>) -> Vec<String> {
    let mut path = vec![remaining[0].clone()];
    loop {
        let cur = path.last().expect("path is never empty");
        let next = upstream[cur]
            .iter()
            .find(|u| remaining.contains(u))
            .expect("a stuck stage has a stuck upstream")
            .clone();
        if let Some(i) = path.iter().position(|p| *p == next) {
            let mut cycle: Vec<String> = path[i..].to_vec();
            cycle.reverse();
            // Start at the stage that comes first in the file.
            let first = (0..cycle.len())
                .min_by_key(|&k| remaining.iter().position(|r| *r == cycle[k]))
                .unwrap_or(0);
            cycle.rotate_left(first);
            cycle.push(cycle[0].clone());
            return cycle;
        }
        path.push(next);
    }
}
