//! The bar's motion: `pipe_mpm`'s neo-Hookean MLS-MPM (PAC-NeRF's "elasticity", the
//! pipeline's `elastic`) with a Young's modulus per particle, set up through the same public
//! path as `pipe simulate` (`pipe::simulate::{SimSpec, Body, frame_step}`: the grid following
//! the particles, gravity, the sticky ground y = 0, and each frame's substeps from the
//! stability limit at its start), in `f64`.

use std::path::Path;

use anyhow::{Context, Result};
use glam::DVec3;
use pipe::simulate::{Body, SimSpec, frame_step};
use pipe_mpm::{Material, NeoHookean, Precision, Simulator};

/// What to simulate.
#[derive(Debug, Clone, PartialEq)]
pub struct Setting {
    /// Rest positions (m).
    pub rest: Vec<DVec3>,
    /// Volume of each particle (m³).
    pub particle_volume: f64,
    /// Grid cell (m).
    pub dx: f64,
    /// Young's modulus per particle (Pa).
    pub youngs_modulus: Vec<f64>,
    /// Poisson's ratio (every particle).
    pub poisson_ratio: f64,
    /// Density (kg/m³).
    pub density: f64,
    /// Initial velocity of every particle (m/s).
    pub v0: DVec3,
    /// Gravity (m/s²).
    pub gravity: DVec3,
    /// Time between frames (s).
    pub frame_dt: f64,
}

/// The positions of every frame (frame 0 = rest) and each frame's substeps (frame 0: 0).
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Positions per frame (m).
    pub frames: Vec<Vec<DVec3>>,
    /// Substeps taken to reach each frame.
    pub substeps: Vec<usize>,
}

impl Setting {
    /// The simulation file this setting is, as `pipe simulate` would read it, with the mean
    /// Young's modulus standing in (the per-particle moduli replace it in [`Self::run`]).
    fn spec(&self) -> Result<SimSpec> {
        let e_mean = self.youngs_modulus.iter().sum::<f64>() / self.youngs_modulus.len() as f64;
        let text = format!(
            "material: {{family: elastic, youngs_modulus: {e_mean:e}, poisson_ratio: {nu:e}, density: {rho:e}}}\n\
             initial_velocity: [{:e}, {:e}, {:e}]\n\
             gravity: [{:e}, {:e}, {:e}]\n\
             particle_volume: {vol:e}\n\
             grid_dx: {dx:e}\n\
             frame_dt: {dt:e}\n\
             fill_interior: false\n\
             boundaries:\n  - {{kind: ground, y: 0.0, condition: sticky}}\n",
            self.v0.x,
            self.v0.y,
            self.v0.z,
            self.gravity.x,
            self.gravity.y,
            self.gravity.z,
            nu = self.poisson_ratio,
            rho = self.density,
            vol = self.particle_volume,
            dx = self.dx,
            dt = self.frame_dt,
        );
        SimSpec::parse(Path::new("<two-material bar>"), &text)
            .context("the two-material bar's simulation settings")
    }

    /// Simulates frames `1..frames` from rest.
    pub fn run(&self, frames: u32) -> Result<Trajectory> {
        let spec = self.spec()?;
        let mut body = Body::new(
            &spec,
            Path::new("<lattice>"),
            self.rest.clone(),
            &[],
            frames,
        )?;
        let n = self.rest.len();
        body.material = Material::from_e_nu_per_particle(
            vec![self.density * self.particle_volume; n],
            vec![self.particle_volume; n],
            &self.youngs_modulus,
            &vec![self.poisson_ratio; n],
        )
        .context("the per-particle material")?;
        let sim = Simulator::new(NeoHookean, body.config(&spec, Precision::F64))
            .context("setting up the simulator")?;
        let mut state = body.state.clone();
        let mut stepper = sim
            .stepper(&mut state, &body.material)
            .context("loading the particles")?;
        let mut out = Trajectory {
            frames: vec![state.x.clone()],
            substeps: vec![0],
        };
        for frame in 1..frames {
            let step = frame_step(&spec, &body, &body.material, &sim, &state, frame)?;
            let t0 = f64::from(frame - 1) * spec.frame_dt;
            stepper
                .advance(t0, spec.frame_dt / step.substeps as f64, step.substeps)
                .with_context(|| format!("simulating frame {frame}"))?;
            stepper.read_motion(&mut state)?;
            out.frames.push(state.x.clone());
            out.substeps.push(step.substeps);
        }
        Ok(out)
    }
}
