//! From the file and the particles to the simulator's settings: particle spacing, cell size,
//! particle volume, domain, colliders and forces.
//!
//! Defaults (each recorded in the summary with where it came from):
//! - spacing `s` = cube root of the volume per particle ([`particle_spacing`]);
//!   `grid_dx = 2 s` and `particle_volume = s³` (PAC-NeRF samples 8 particles per `dx³` cell);
//! - a *surface-like* cloud (no cell of the density measure lies inside it: 3DGS splats, a
//!   scanned surface) has no volume density: `grid_dx` = its largest extent / 24
//!   ([`SURFACE_CELLS_ACROSS`]), it is filled with particles when closed ([`super::fill`];
//!   `fill_interior` in the file forces or forbids it), and its particles get the volumes the
//!   filling measured (3DGS splats: the solid's voxels they lie in; points: their wall's
//!   volume, shared evenly); a floor closes it underneath when it rests on a ground plane;
//! - no domain: the grid follows the particles (`pipe_mpm::Domain::Follow`): each substep's
//!   grid covers their box plus the stencil margin, so nothing but the declared boundaries
//!   acts on them, at most [`FOLLOW_NODES`] nodes (a run whose particles spread wider stops
//!   with an error naming the extent). A `domain` in the file fixes the grid instead, with
//!   separating walls at its faces that hold and count the particles reaching them.
//!
//! A grid over [`MAX_GRID_NODES`] (a file domain) or [`FOLLOW_NODES`] (the particles' own box)
//! is refused before anything runs, naming `domain` (a file domain too large) or `grid_dx`
//! (the particles' box alone too large for it, with the smallest `grid_dx` that keeps it
//! under [`MAX_NODES`]).

use std::path::Path;

use glam::DVec3;
use pipe_mpm::{Aabb, Collider, FOLLOW_MAX_NODES, MAX_GRID_NODES, ParticleForce};

use super::SimulateError;
use super::fill::{Floor, MAX_FILL_VOXELS, Splat, down_axis, fill_interior};
use super::spec::{BoundarySpec, BoxSpec, ForceSpec, ParticleSet, SimSpec, fmt_num, short_number};
use crate::scene::neighbors::{Spacing, bounds, particle_spacing};

/// The `grid_dx` a refusal suggests keeps the particles' box under this many nodes (about
/// 230 MB of node buffers), room for the motion below [`FOLLOW_NODES`].
pub const MAX_NODES: f64 = 4_194_304.0;

/// Most nodes a grid that follows the particles may span.
pub const FOLLOW_NODES: usize = FOLLOW_MAX_NODES;

/// Grid cells across the largest extent of a surface-like cloud (PAC-NeRF's torus, 0.45 m at
/// dx = 0.02 m, has 22). A filled ball then holds ~58k particles (8 per cell).
pub const SURFACE_CELLS_ACROSS: f64 = 24.0;

/// The simulator margin in cells (see `SimConfig::margin`).
pub(crate) const GRID_MARGIN: usize = 3;

/// Resolved scene settings.
#[derive(Debug, Clone)]
pub struct Setup {
    /// Measured spacing (when a default needed it).
    pub spacing: Option<Spacing>,
    /// Cell size (m).
    pub dx: f64,
    /// `"file"` or `"2 x spacing"`.
    pub dx_source: String,
    /// Particle volume (m³); their mean when `input_volumes` are given.
    pub particle_volume: f64,
    /// `"file"`, `"spacing^3"` or how the filling gave it.
    pub volume_source: String,
    /// Each input particle's volume (m³) when the filling measured them; `None`: all
    /// `particle_volume`.
    pub input_volumes: Option<Vec<f64>>,
    /// Particles added inside a closed surface (m), simulated after the input ones, not written.
    pub fill: Vec<DVec3>,
    /// Volume of a whole filler particle, the filling's voxel (m³).
    pub fill_volume: f64,
    /// Each filler's volume (m³): `fill_volume`, or half of it next to the surface.
    pub fill_volumes: Vec<f64>,
    /// What the filling did, for the summary (`"off"`, `"no: the cloud is volumetric"`, ...).
    pub fill_source: String,
    /// The file's domain (m): a fixed grid with walls; `None`: the grid follows the particles.
    pub domain: Option<Aabb>,
    /// How the grid was chosen.
    pub domain_source: String,
    /// Colliders, in file order.
    pub colliders: Vec<Collider>,
    /// Forces with resolved particle indices.
    pub forces: Vec<ParticleForce>,
    /// The particles that carry the input splats and how they ride them, when splats sharing
    /// a voxel were merged (`merge_splats`); `None`: each input is a particle.
    pub carriers: Option<(Vec<DVec3>, super::skin::Skin)>,
    /// Things the user should know.
    pub warnings: Vec<String>,
}

/// Resolves the settings for `x0` (m), read from `particles`, simulated for `frames` frames.
pub fn setup(
    spec: &SimSpec,
    particles: &Path,
    (x0, splats): (&[DVec3], &[Splat]),
    frames: u32,
) -> Result<Setup, SimulateError> {
    let mut warnings = Vec::new();
    let sizes_given = spec.grid_dx.is_some() && spec.particle_volume.is_some();
    let spacing = if !sizes_given || spec.fill_interior.is_none() {
        let sp = particle_spacing(x0);
        if sp.is_none() && !sizes_given {
            return Err(SimulateError::Spacing {
                path: particles.to_path_buf(),
                message: format!(
                    "cannot measure the particle spacing from {} particle(s) with fewer than two \
                     distinct positions; set `grid_dx` and `particle_volume` in {}",
                    x0.len(),
                    spec.file.display()
                ),
            });
        }
        sp
    } else {
        None
    };
    let surface_like = spacing.is_some_and(|sp| sp.interior_cells == 0);
    let (lo0, hi0) = bounds(x0).expect("particles are not empty");
    let (dx, dx_source) = match (spec.grid_dx, spacing) {
        (Some(dx), _) => (dx, "file".to_string()),
        (None, Some(sp)) if surface_like => {
            let across = (hi0 - lo0).max_element() / SURFACE_CELLS_ACROSS;
            if across > 2.0 * sp.median_nn {
                (
                    across,
                    format!("largest extent / {SURFACE_CELLS_ACROSS} (a surface-like cloud)"),
                )
            } else {
                (
                    2.0 * sp.median_nn,
                    "2 x median nearest-neighbour distance".to_string(),
                )
            }
        }
        (None, Some(sp)) => (2.0 * sp.spacing, "2 x spacing".to_string()),
        (None, None) => unreachable!("spacing is measured when grid_dx is missing"),
    };
    let fill_wanted = spec.fill_interior.unwrap_or(surface_like);
    let voxels = if fill_wanted || (surface_like && spec.particle_volume.is_none()) {
        let floor = ground_under(spec, x0);
        let f = fill_interior(x0, splats, 0.5 * dx, floor, MAX_FILL_VOXELS);
        if f.is_none() {
            warnings.push(format!(
                "the interior was not measured nor filled: the particles' box needs more than \
                 {MAX_FILL_VOXELS} voxels of dx/2 = {} m; a larger `grid_dx` allows it",
                short_number(0.5 * dx)
            ));
        }
        f
    } else {
        None
    };
    // Splats always have a solid (their field's wall and what it encloses); points only when
    // their surface encloses something.
    let splat_solid = !splats.is_empty();
    let closed = voxels
        .as_ref()
        .is_some_and(|f| splat_solid || (f.enclosed_voxels > 0 && !f.points.is_empty()));
    let fill_source = match (&voxels, fill_wanted, closed) {
        (_, false, _) if spec.fill_interior == Some(false) => "off (file)".to_string(),
        (_, false, _) => "no: the cloud is volumetric".to_string(),
        (None, true, _) => "no: too many voxels".to_string(),
        (Some(f), true, false) if spec.fill_interior == Some(true) => {
            warnings.push(format!(
                "nothing is enclosed at the filling's voxel size {} m: the particles fill \
                 their volume already, or their surface has gaps wider than four voxels (two \
                 grid cells) that let the outside in, and is simulated as a shell; a larger \
                 `grid_dx` closes wider gaps",
                short_number(f.voxel)
            ));
            "no: nothing enclosed".to_string()
        }
        (Some(_), true, false) => "no: nothing enclosed (a solid or an open surface)".to_string(),
        (Some(f), true, true) => format!(
            "{} particle(s) inside the {}, on a {} m lattice, solid {} m^3 ({})",
            f.points.len(),
            if splat_solid {
                "splats' solid"
            } else {
                "closed surface"
            },
            short_number(f.voxel),
            short_number(f.solid_volume()),
            if spec.fill_interior == Some(true) {
                "file"
            } else {
                "a surface-like cloud"
            }
        ),
    };
    if surface_like && spec.grid_dx.is_none() {
        warnings.push(format!(
            "the cloud is surface-like (no particle lies deep inside it, as with 3DGS splats): \
             grid_dx = {} m ({dx_source}); filling: {fill_source}; set `grid_dx`, \
             `particle_volume` and `fill_interior` if that is wrong",
            short_number(dx)
        ));
    }
    let (particle_volume, volume_source, input_volumes) =
        match (spec.particle_volume, spacing, &voxels) {
            (Some(v), _, _) => (v, "file".to_string(), None),
            (None, _, Some(f)) if (fill_wanted && closed) || surface_like => (
                f.input_volume() / x0.len() as f64,
                if splat_solid {
                    "the solid's voxels each splat lies in (mean)"
                } else {
                    "the surface layer's voxels / particles"
                }
                .to_string(),
                Some(f.input_volumes.clone()),
            ),
            (None, Some(sp), _) => (sp.spacing.powi(3), "spacing^3".to_string(), None),
            (None, None, _) => {
                unreachable!("spacing is measured when particle_volume is missing")
            }
        };
    // Splats that share a voxel of the filling ride one particle ([`super::skin`]).
    let merged = match (&voxels, spec.merge_splats && !splats.is_empty()) {
        (Some(f), true) if fill_wanted && closed => Some(super::skin::merge(
            x0,
            &f.input_voxels,
            input_volumes.as_deref().unwrap_or(&f.input_volumes),
        )),
        _ => None,
    };
    let inputs = x0;
    let (x0, input_volumes, particle_volume) = match &merged {
        Some(m) => (
            m.particles.as_slice(),
            Some(m.volumes.clone()),
            m.volumes.iter().sum::<f64>() / m.volumes.len().max(1) as f64,
        ),
        None => (x0, input_volumes, particle_volume),
    };
    warnings.extend(size_warnings(
        spec,
        spacing.filter(|_| !surface_like),
        dx,
        particle_volume,
        x0.len(),
    ));
    warnings.extend(particles_inside_boundaries(&spec.boundaries, x0, dx));
    let (fill, fill_volume, fill_volumes) = match voxels {
        Some(f) if fill_wanted && closed => {
            let v = f.filler_volume();
            (f.points, v, f.filler_volumes)
        }
        _ => (Vec::new(), 0.0, Vec::new()),
    };
    let colliders: Vec<Collider> = spec
        .boundaries
        .iter()
        .map(|b| match *b {
            BoundarySpec::Ground { y, condition } => Collider::ground(y, condition.kind()),
            BoundarySpec::HalfSpace {
                point,
                normal,
                condition,
            } => Collider::HalfSpace {
                point: DVec3::from_array(point),
                normal: DVec3::from_array(normal),
                kind: condition.kind(),
            },
            BoundarySpec::Box { aabb, condition } => Collider::Box {
                aabb: Aabb::new(DVec3::from_array(aabb.min), DVec3::from_array(aabb.max)),
                kind: condition.kind(),
            },
            BoundarySpec::Anchor { ref still } => Collider::Anchor {
                cells: std::sync::Arc::new(anchor_cells(still, x0, dx)),
                cell: dx,
            },
        })
        .collect();
    let forces = spec
        .forces
        .iter()
        .enumerate()
        .map(|(i, f)| resolve_force(spec, i, f, x0, inputs.len(), merged.as_ref()))
        .collect::<Result<Vec<_>, _>>()?;
    warnings.extend(forces_outside_time(
        &forces,
        f64::from(frames.saturating_sub(1)) * spec.frame_dt,
    ));
    let (domain, domain_source) = match spec.domain {
        Some(b) => {
            let d = Aabb::new(DVec3::from_array(b.min), DVec3::from_array(b.max));
            let outside = x0.iter().filter(|p| !d.contains(**p)).count();
            if outside > 0 {
                warnings.push(format!(
                    "{outside} particle(s) start outside `domain`; they are moved to its edge"
                ));
            }
            (
                Some(d),
                "file (walls at its faces hold the particles that reach them)".to_string(),
            )
        }
        None => (
            None,
            format!(
                "none: the grid follows the particles (each substep's grid covers their box plus \
                 the stencil margin, at most {FOLLOW_NODES} nodes)"
            ),
        ),
    };
    let (nodes, budget) = match domain {
        Some(d) => (node_count(&d, dx), MAX_GRID_NODES),
        None => (node_count(&Aabb::new(lo0, hi0), dx), FOLLOW_NODES as f64),
    };
    if nodes > budget {
        return Err(grid_too_large(
            spec,
            particles,
            (dx, &dx_source),
            spec.domain.is_some(),
            (lo0, hi0),
            (nodes, budget),
        ));
    }
    Ok(Setup {
        spacing,
        dx,
        dx_source,
        particle_volume,
        volume_source,
        input_volumes,
        fill,
        fill_volume,
        fill_volumes,
        fill_source,
        domain,
        domain_source,
        colliders,
        forces,
        warnings,
        carriers: merged.map(|m| (m.particles, m.skin)),
    })
}

/// The ground plane the particles `x0` (m) may rest on: the boundary plane facing up against
/// gravity (a `ground`, or a `half_space` whose normal is that axis) nearest their lowest
/// point; the filling lays a floor on it only when the object is that close to it.
fn ground_under(spec: &SimSpec, x0: &[DVec3]) -> Option<Floor> {
    let (axis, negative) = down_axis(DVec3::from_array(spec.gravity))?;
    let up = if negative { 1.0 } else { -1.0 };
    let lowest = x0
        .iter()
        .map(|p| up * p[axis])
        .fold(f64::INFINITY, f64::min);
    spec.boundaries
        .iter()
        .filter_map(|b| {
            let (point, normal) = match *b {
                BoundarySpec::Ground { y, .. } => (DVec3::new(0.0, y, 0.0), DVec3::Y),
                BoundarySpec::HalfSpace { point, normal, .. } => {
                    (DVec3::from_array(point), DVec3::from_array(normal))
                }
                BoundarySpec::Box { .. } | BoundarySpec::Anchor { .. } => return None,
            };
            // A plane across the down axis, its free side up.
            let facing = up * normal[axis] / normal.length();
            (facing > 0.999).then_some(up * point[axis])
        })
        .min_by(|a, b| (a - lowest).abs().total_cmp(&(b - lowest).abs()))
        .map(|level| Floor {
            down: (axis, negative),
            level: up * level,
        })
}

/// Warnings for a `grid_dx` or `particle_volume` from the file that the measured `spacing` of a
/// volumetric cloud of `n` particles contradicts: a grid finer than the spacing (cells between
/// particles get no mass, so the body cannot hold together), or a particle volume over 100×
/// off the volume each particle occupies (a unit slip: mm³ or cm³ for m³).
fn size_warnings(
    spec: &SimSpec,
    spacing: Option<Spacing>,
    dx: f64,
    particle_volume: f64,
    n: usize,
) -> Vec<String> {
    let Some(s) = spacing.map(|sp| sp.spacing) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    let per_cell = (dx / s).powi(3);
    if spec.grid_dx.is_some() && per_cell < 1.0 {
        out.push(format!(
            "`grid_dx` = {} m is below the particle spacing {} m: about {} particle(s) per \
             cell (PAC-NeRF samples 8). Cells between particles get no mass, so the body \
             cannot hold together and falls apart; about twice the spacing ({} m) keeps it \
             whole",
            fmt_num(dx),
            short_number(s),
            short_number(per_cell),
            short_number(2.0 * s)
        ));
    }
    let ratio = particle_volume / s.powi(3);
    if spec.particle_volume.is_some() && !(0.01..=100.0).contains(&ratio) {
        let rho = spec.material.density;
        out.push(format!(
            "`particle_volume` = {} m^3 is {}x the volume each particle occupies in the cloud \
             (spacing {} m, cubed {} m^3): the {n} particles weigh {} kg at {} kg/m^3 instead \
             of about {} kg; check its units (m^3)",
            fmt_num(particle_volume),
            if (10.0..1e4).contains(&ratio) {
                format!("{ratio:.0}")
            } else {
                short_number(ratio)
            },
            short_number(s),
            short_number(s.powi(3)),
            short_number(rho * particle_volume * n as f64),
            fmt_num(rho),
            short_number(rho * s.powi(3) * n as f64),
        ));
    }
    out
}

/// How deep (m) `x` lies inside the solid side of boundary `b` (negative: on the free side).
pub fn depth_inside(b: &BoundarySpec, x: DVec3) -> f64 {
    match b {
        BoundarySpec::Ground { y, .. } => y - x.y,
        BoundarySpec::HalfSpace { point, normal, .. } => {
            -(x - DVec3::from_array(*point)).dot(DVec3::from_array(*normal))
        }
        BoundarySpec::Box { aabb, .. } => (x - DVec3::from_array(aabb.min))
            .min(DVec3::from_array(aabb.max) - x)
            .min_element(),
        // Holding the particles next to the still points is what an anchor is for.
        BoundarySpec::Anchor { .. } => f64::NEG_INFINITY,
    }
}

/// The cells (integer coordinates of the nodes, lattice of edge `dx`, m) an anchor holds: the
/// nodes within `dx` of every still point that has a particle of `x0` within `2·dx` (a node
/// held there lies inside the quadratic B-spline support, 1.5 cells, of that particle).
pub fn anchor_cells(
    still: &[[f64; 3]],
    x0: &[DVec3],
    dx: f64,
) -> std::collections::HashSet<[i32; 3]> {
    let cell = |p: DVec3| {
        let k = (p / dx).round();
        [k.x as i32, k.y as i32, k.z as i32]
    };
    let mut buckets: std::collections::HashMap<[i32; 3], Vec<DVec3>> =
        std::collections::HashMap::new();
    for p in x0 {
        buckets.entry(cell(*p)).or_default().push(*p);
    }
    let around = |c: [i32; 3], r: i32| {
        (-r..=r).flat_map(move |i| {
            (-r..=r).flat_map(move |j| (-r..=r).map(move |k| [c[0] + i, c[1] + j, c[2] + k]))
        })
    };
    let reach = 2.0 * dx;
    let mut out = std::collections::HashSet::new();
    for s in still {
        let s = DVec3::from_array(*s);
        let c = cell(s);
        let near = around(c, 3).any(|n| {
            buckets
                .get(&n)
                .is_some_and(|ps| ps.iter().any(|p| (*p - s).length() <= reach))
        });
        if !near {
            continue;
        }
        for n in around(c, 1) {
            let node = DVec3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2])) * dx;
            if (node - s).length() <= dx {
                out.insert(n);
            }
        }
    }
    out
}

/// A warning per boundary that particles start inside, more than half a cell deep: its
/// condition acts on them from the first substep (sticky: they never move), which a
/// misplaced plane or box, or a wrong sign, causes.
fn particles_inside_boundaries(boundaries: &[BoundarySpec], x0: &[DVec3], dx: f64) -> Vec<String> {
    let names = describe_boundaries(boundaries, false);
    boundaries
        .iter()
        .enumerate()
        .filter_map(|(i, b)| {
            let inside = x0
                .iter()
                .filter(|&&x| depth_inside(b, x) > 0.5 * dx)
                .count();
            (inside > 0).then(|| {
                format!(
                    "{inside} of the {} particles start inside `boundaries[{i}]` ({}), more \
                     than half a cell deep: its condition holds them from the first substep \
                     (sticky: they do not move); move the boundary or the particles if that is \
                     wrong",
                    x0.len(),
                    names[i]
                )
            })
        })
        .collect()
}

/// A warning per force or impulse that acts only outside the simulated time `[0, t_end)` (s).
fn forces_outside_time(forces: &[ParticleForce], t_end: f64) -> Vec<String> {
    let when = |f: &ParticleForce| match *f {
        ParticleForce::Force { start, end, .. } if end <= 0.0 || start >= t_end => {
            Some(format!("from t = {} s", short_number(start)))
        }
        ParticleForce::Impulse { time, .. } if time < 0.0 || time >= t_end => {
            Some(format!("at t = {} s", short_number(time)))
        }
        _ => None,
    };
    forces
        .iter()
        .enumerate()
        .filter_map(|(i, f)| {
            when(f).map(|w| {
                format!(
                    "`forces[{i}]` acts {w}, outside the simulated time [0, {}) s: it has no \
                     effect",
                    short_number(t_end)
                )
            })
        })
        .collect()
}

/// Grid nodes for a domain (the simulator's layout: margin cells on each side).
pub fn grid_nodes(domain: &Aabb, dx: f64) -> [usize; 3] {
    let lo = (domain.lo / dx).floor() - DVec3::splat(GRID_MARGIN as f64);
    let hi = (domain.hi / dx).ceil() + DVec3::splat(GRID_MARGIN as f64);
    let d = hi - lo + DVec3::ONE;
    [d.x as usize, d.y as usize, d.z as usize]
}

fn node_count(domain: &Aabb, dx: f64) -> f64 {
    grid_nodes(domain, dx).iter().map(|&n| n as f64).product()
}

/// The error for a grid of `nodes` over its `budget`: it names `domain` when the particles'
/// own box would fit at this `dx`, else `grid_dx` (or the spacing it was derived from), with
/// the smallest `dx` that keeps the particles' box under [`MAX_NODES`].
fn grid_too_large(
    spec: &SimSpec,
    particles: &Path,
    (dx, dx_source): (f64, &str),
    domain_from_file: bool,
    (lo0, hi0): (DVec3, DVec3),
    (nodes, budget): (f64, f64),
) -> SimulateError {
    let pad = |dx: f64| Aabb::new(lo0 - DVec3::splat(4.0 * dx), hi0 + DVec3::splat(4.0 * dx));
    let size = (hi0 - lo0).to_array().map(short_number);
    let across = format!(
        "the particles span {} x {} x {} m",
        size[0], size[1], size[2]
    );
    let what = format!(
        "the grid would have {nodes:.3e} nodes at dx = {} m, more than the {budget:.3e} a \
         run can hold",
        short_number(dx)
    );
    if domain_from_file && node_count(&pad(dx), dx) <= budget {
        return spec.error_at(
            "domain",
            format!("invalid `domain`: {what}"),
            Some(format!(
                "{across}; choose a smaller `domain` or a larger `grid_dx`"
            )),
        );
    }
    // Smallest dx (two significant digits, rounded up) whose padded particle box fits.
    let mut fit = dx * (node_count(&pad(dx), dx) / MAX_NODES).cbrt();
    while node_count(&pad(fit), fit) > MAX_NODES {
        fit *= 1.05;
    }
    let scale = 10f64.powf(fit.log10().floor() - 1.0);
    let fit = format!("{:.1e}", (fit / scale).ceil() * scale);
    if dx_source == "file" {
        spec.error_at(
            "grid_dx",
            format!("invalid `grid_dx` = {}: {what}", fmt_num(dx)),
            Some(format!(
                "{across}; `grid_dx` >= {fit} m keeps the grid under {MAX_NODES} nodes"
            )),
        )
    } else {
        SimulateError::Spacing {
            path: particles.to_path_buf(),
            message: format!(
                "{what} (dx = {dx_source} from the measured particle spacing; {across}); set \
                 `grid_dx` in {} (>= {fit} m keeps the grid under {MAX_NODES} nodes)",
                spec.file.display()
            ),
        }
    }
}

fn resolve_force(
    spec: &SimSpec,
    i: usize,
    f: &ForceSpec,
    x0: &[DVec3],
    inputs: usize,
    merged: Option<&super::skin::Merged>,
) -> Result<ParticleForce, SimulateError> {
    let path = format!("forces[{i}].particles");
    let set = match f {
        ForceSpec::Force { particles, .. } | ForceSpec::Impulse { particles, .. } => particles,
    };
    let particles: Vec<usize> = match set {
        ParticleSet::All => (0..x0.len()).collect(),
        ParticleSet::Indices(ids) => {
            if let Some((j, &bad)) = ids.iter().enumerate().find(|(_, p)| **p >= inputs as u64) {
                return Err(spec.error_at(
                    &format!("{path}[{j}]"),
                    format!("invalid `{path}[{j}]` = {bad}"),
                    Some(format!(
                        "the input has {inputs} particles (indices 0 to {})",
                        inputs - 1
                    )),
                ));
            }
            match merged {
                // The particles that carry the listed splats, each once.
                Some(m) => {
                    let mut c: Vec<usize> = ids
                        .iter()
                        .map(|&p| m.skin.carrier()[p as usize] as usize)
                        .collect();
                    c.sort_unstable();
                    c.dedup();
                    c
                }
                None => ids.iter().map(|&p| p as usize).collect(),
            }
        }
        ParticleSet::Box(BoxSpec { min, max }) => {
            let b = Aabb::new(DVec3::from_array(*min), DVec3::from_array(*max));
            let sel: Vec<usize> = (0..x0.len()).filter(|&p| b.contains(x0[p])).collect();
            if sel.is_empty() {
                let (lo, hi) = bounds(x0).expect("particles are not empty");
                return Err(spec.error_at(
                    &path,
                    format!("the box `{path}` {{min: {min:?}, max: {max:?}}} selects no particle"),
                    Some(format!(
                        "the initial particles span {:?} to {:?} m",
                        lo.to_array(),
                        hi.to_array()
                    )),
                ));
            }
            sel
        }
    };
    Ok(match *f {
        ForceSpec::Force {
            force, start, end, ..
        } => ParticleForce::Force {
            particles,
            force: DVec3::from_array(force),
            start,
            end: end.unwrap_or(f64::MAX),
        },
        ForceSpec::Impulse { impulse, time, .. } => ParticleForce::Impulse {
            particles,
            impulse: DVec3::from_array(impulse),
            time,
        },
    })
}

/// One line per boundary, for the summary (the domain walls last, when there is a domain).
pub fn describe_boundaries(boundaries: &[BoundarySpec], domain: bool) -> Vec<String> {
    let name = |c: &super::spec::Condition| match c {
        super::spec::Condition::Sticky => "sticky",
        super::spec::Condition::Slip => "slip",
        super::spec::Condition::Separate => "separate",
    };
    let mut out: Vec<String> = boundaries
        .iter()
        .map(|b| match b {
            BoundarySpec::Ground { y, condition } => {
                format!("ground y = {} m ({})", fmt_num(*y), name(condition))
            }
            BoundarySpec::HalfSpace {
                point,
                normal,
                condition,
            } => format!(
                "half_space through {point:?} m, normal {normal:?} ({})",
                name(condition)
            ),
            BoundarySpec::Box { aabb, condition } => format!(
                "box {:?} to {:?} m ({})",
                aabb.min,
                aabb.max,
                name(condition)
            ),
            BoundarySpec::Anchor { still } => format!(
                "anchor: the grid next to {} Gaussians that do not simulate (sticky)",
                still.len()
            ),
        })
        .collect();
    if domain {
        out.push("domain walls (separate; particles reaching them are held and counted)".into());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(text: &str) -> SimSpec {
        SimSpec::parse(Path::new("sim.yaml"), text).unwrap()
    }

    fn block() -> Vec<DVec3> {
        (0..4)
            .flat_map(|i| (0..4).flat_map(move |j| (0..4).map(move |k| (i, j, k))))
            .map(|(i, j, k)| DVec3::new(i as f64, 10.0 + j as f64, k as f64) * 0.01)
            .collect()
    }

    const MAT: &str =
        "material: {family: elastic, youngs_modulus: 1e5, poisson_ratio: 0.3, density: 1000}\n";

    #[test]
    fn without_a_domain_the_grid_follows_the_particles() {
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 0.02\nparticle_volume: 1e-6\n\
             initial_velocity: [1, 2, 0]\nboundaries: [{{kind: ground, y: 0}}]\n"
        ));
        let x = block();
        let st = setup(&s, Path::new("p.ply"), (&x, &[]), 26).unwrap();
        assert_eq!((st.dx, st.particle_volume), (0.02, 1e-6));
        assert_eq!(st.domain, None);
        assert!(st.domain_source.starts_with("none: the grid follows"));
        assert!(st.warnings.is_empty());
        let with = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 0.02\nparticle_volume: 1e-6\n\
             domain: {{min: [-1, 0, -1], max: [1, 2, 1]}}\n"
        ));
        let st = setup(&with, Path::new("p.ply"), (&x, &[]), 26).unwrap();
        assert_eq!(
            st.domain,
            Some(Aabb::new(
                DVec3::new(-1.0, 0.0, -1.0),
                DVec3::ONE * DVec3::new(1.0, 2.0, 1.0)
            ))
        );
    }

    /// A 16³ lattice of spacing 1 cm whose lowest layer is at y = 0.1 m.
    fn lattice() -> Vec<DVec3> {
        (0..16)
            .flat_map(|i| (0..16).flat_map(move |j| (0..16).map(move |k| (i, j, k))))
            .map(|(i, j, k)| DVec3::new(i as f64, 10.0 + j as f64, k as f64) * 0.01)
            .collect()
    }

    #[test]
    fn a_grid_finer_than_the_spacing_or_a_volume_in_other_units_is_warned() {
        let x = lattice();
        let run = |sizes: &str| {
            let s = spec(&format!("{MAT}frame_dt: 0.04\n{sizes}"));
            setup(&s, Path::new("p.ply"), (&x, &[]), 2)
                .unwrap()
                .warnings
        };
        // PAC-NeRF's sampling: dx = 2 s, V = s³.
        assert!(run("grid_dx: 0.02\nparticle_volume: 1e-6\n").is_empty());
        let w = run("grid_dx: 0.004\nparticle_volume: 1e-3\n");
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(
            w[0].starts_with("`grid_dx` = 0.004 m is below the particle spacing 0.0100 m")
                && w[0].contains("about twice the spacing (0.0200 m)"),
            "{w:?}"
        );
        assert!(
            w[1].starts_with("`particle_volume` = 0.001 m^3 is 1000x the volume")
                && w[1].contains("4096 particles weigh 4096 kg"),
            "{w:?}"
        );
        // Within 100x either way, nothing.
        assert!(run("grid_dx: 0.01\nparticle_volume: 5e-5\n").is_empty());
    }

    #[test]
    fn particles_starting_inside_a_boundary_are_counted() {
        let x = lattice();
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 0.02\nparticle_volume: 1e-6\nboundaries:\n\
             - {{kind: ground, y: 0.15}}\n\
             - {{kind: box, min: [-1, -1, -1], max: [0.035, 1, 1]}}\n\
             - {{kind: ground, y: 0.105}}\n"
        ));
        let w = setup(&s, Path::new("p.ply"), (&x, &[]), 2)
            .unwrap()
            .warnings;
        // Deeper than dx/2 = 1 cm: layers y = 0.10–0.13 below the first ground, x = 0–0.02 in
        // the box; the last ground is under half a cell above the lowest layer.
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(
            w[0].starts_with("1024 of the 4096 particles start inside `boundaries[0]` (ground y = 0.15 m (sticky))"),
            "{w:?}"
        );
        assert!(
            w[1].starts_with("768 of the 4096 particles start inside `boundaries[1]`"),
            "{w:?}"
        );
    }

    /// The number after `marker` in `msg`.
    fn number_after(msg: &str, marker: &str) -> f64 {
        let rest = &msg[msg.find(marker).expect(msg) + marker.len()..];
        let end = rest.find(' ').unwrap_or(rest.len());
        rest[..end].parse().expect(msg)
    }

    #[test]
    fn a_grid_too_large_names_grid_dx_and_a_dx_that_fits() {
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 1e-5\nparticle_volume: 1e-6\n"
        ));
        let e = setup(&s, Path::new("p.ply"), (&block(), &[]), 2).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.starts_with("sim.yaml: invalid `grid_dx` = 1e-5: the grid would have")
                && msg.contains("at line 3:")
                && msg.contains("the particles span 0.0300 x 0.0300 x 0.0300 m"),
            "{msg}"
        );
        // The suggested dx runs, without a warning that the particles' box alone is too big.
        let fit = number_after(&msg, "`grid_dx` >= ");
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: {fit}\nparticle_volume: 1e-6\n"
        ));
        let st = setup(&s, Path::new("p.ply"), (&block(), &[]), 2).unwrap();
        assert!(
            st.domain.is_none() && st.warnings.is_empty(),
            "{:?}",
            st.warnings
        );
    }

    #[test]
    fn a_file_domain_too_large_names_domain() {
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 0.001\nparticle_volume: 1e-6\n\
             domain: {{min: [-100, -100, -100], max: [100, 100, 100]}}\n"
        ));
        let msg = setup(&s, Path::new("p.ply"), (&block(), &[]), 2)
            .unwrap_err()
            .to_string();
        assert!(
            msg.starts_with("sim.yaml: invalid `domain`: the grid would have 8.0")
                && msg.contains("choose a smaller `domain`"),
            "{msg}"
        );
    }

    #[test]
    fn a_measured_dx_too_small_for_the_cloud_asks_for_grid_dx() {
        // Two dense solid clusters 1 km apart: dx = 2 × 1e-4 m over a 1 km box.
        let mut x = Vec::new();
        for c in [0.0, 1000.0] {
            for (i, j, k) in
                (0..16).flat_map(|i| (0..16).flat_map(move |j| (0..16).map(move |k| (i, j, k))))
            {
                x.push(DVec3::new(
                    c + i as f64 * 1e-4,
                    j as f64 * 1e-4,
                    k as f64 * 1e-4,
                ));
            }
        }
        let s = spec(&format!("{MAT}frame_dt: 0.04\n"));
        let msg = setup(&s, Path::new("p.ply"), (&x, &[]), 2)
            .unwrap_err()
            .to_string();
        assert!(
            msg.starts_with("p.ply: the grid would have")
                && msg.contains("from the measured particle spacing")
                && msg.contains("set `grid_dx` in sim.yaml (>= "),
            "{msg}"
        );
    }

    #[test]
    fn one_particle_needs_explicit_sizes() {
        let s = spec(&format!("{MAT}frame_dt: 0.04\n"));
        let e = setup(&s, Path::new("p.ply"), (&[DVec3::ONE], &[]), 2).unwrap_err();
        assert!(
            e.to_string()
                .contains("p.ply: cannot measure the particle spacing from 1 particle"),
            "{e}"
        );
        let s = spec(&format!(
            "{MAT}frame_dt: 0.04\ngrid_dx: 0.1\nparticle_volume: 1e-4\n"
        ));
        assert!(setup(&s, Path::new("p.ply"), (&[DVec3::ONE], &[]), 2).is_ok());
    }

    /// A still point anchors only within two cells of a particle, and holds the nodes within a
    /// cell of itself.
    #[test]
    fn an_anchor_holds_the_nodes_next_to_still_points_that_touch_the_body() {
        let dx = 0.01;
        let body = [DVec3::new(0.0, 0.0, 0.0), DVec3::new(0.01, 0.0, 0.0)];
        let near = anchor_cells(&[[0.029, 0.0, 0.0]], &body, dx);
        assert!(!near.is_empty());
        for c in &near {
            let node = DVec3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2])) * dx;
            assert!((node - DVec3::new(0.029, 0.0, 0.0)).length() <= dx + 1e-12);
        }
        assert!(near.contains(&[3, 0, 0]) && near.contains(&[2, 0, 0]));
        assert!(anchor_cells(&[[0.035, 0.0, 0.0]], &body, dx).is_empty());
        assert!(anchor_cells(&[], &body, dx).is_empty());
    }
}
