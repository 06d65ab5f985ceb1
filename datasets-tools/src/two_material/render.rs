//! A small ray tracer that is not the Gaussian rasterizer being fitted: the body the particles
//! stand for ([`Surface`], marched per sample) or a sphere per particle (an exact ray–sphere
//! test against a depth buffer), Lambert-shaded, over a backdrop of a tiled floor mat on the ground y = 0, a plain floor around it and a
//! round wall (a vertical cylinder about the y axis) with a vertical colour gradient.
//!
//! Each pixel is the mean of `ss × ss` samples at `((x + (i + ½)/ss), (y + (j + ½)/ss))`; the
//! object's coverage (samples that hit it / ss²) is its alpha mask. The backdrop is the
//! same in every frame and casts and receives no shadow, so the background plate is the render
//! without the object and every pixel the object does not touch equals it exactly.

use glam::DVec3;
use pipe::scene::camera::Camera;
use rayon::prelude::*;

use super::surface::Surface;

/// The light, the backdrop and the sampling.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Look {
    /// Unit direction towards the (directional) light.
    pub to_light: DVec3,
    /// Ambient term: a surface facing away from the light gets `ambient · albedo`.
    pub ambient: f64,
    /// Diffuse term: `(ambient + diffuse · max(0, n·l)) · albedo`.
    pub diffuse: f64,
    /// Samples per pixel along each axis.
    pub ss: u32,
    /// Side of a floor tile (m).
    pub tile: f64,
    /// Half the side of the square tiled mat centred on the origin (m).
    pub mat_half: f64,
    /// Radius of the round wall (m).
    pub wall_radius: f64,
}

impl Default for Look {
    fn default() -> Self {
        Self {
            to_light: DVec3::new(0.35, 1.0, 0.55).normalize(),
            ambient: 0.4,
            diffuse: 0.6,
            ss: 3,
            tile: 0.1,
            mat_half: 1.0,
            wall_radius: 3.0,
        }
    }
}

const TILE_LIGHT: [f64; 3] = [196.0, 192.0, 182.0];
const TILE_DARK: [f64; 3] = [122.0, 120.0, 114.0];
const FLOOR: [f64; 3] = [150.0, 152.0, 156.0];
const WALL_LOW: [f64; 3] = [206.0, 214.0, 226.0];
const WALL_HIGH: [f64; 3] = [120.0, 146.0, 190.0];

/// An image's samples: colour (0–255, unrounded) and whether an object covers them.
#[derive(Debug, Clone, PartialEq)]
pub struct Samples {
    /// Samples per row (`width · ss`).
    pub sw: usize,
    /// Sample rows (`height · ss`).
    pub sh: usize,
    /// Colour per sample.
    pub rgb: Vec<[f64; 3]>,
    /// `true` where an object covers the sample.
    pub object: Vec<bool>,
}

/// A frame rendered: 8-bit RGB and the object's coverage as 8-bit alpha.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Row-major RGB, `width · height · 3` bytes.
    pub rgb: Vec<u8>,
    /// Row-major coverage, `round(255 · covered samples / ss²)`.
    pub alpha: Vec<u8>,
}

/// The world-space ray through sample `(sx, sy)`: origin and unit direction.
fn ray(cam: &Camera, ss: u32, sx: usize, sy: usize) -> (DVec3, DVec3) {
    let s = f64::from(ss);
    let u = (sx as f64 + 0.5) / s;
    let v = (sy as f64 + 0.5) / s;
    let d_cam = DVec3::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
    (
        cam.centre_world,
        (cam.world_from_camera_rot * d_cam).normalize(),
    )
}

fn lerp(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    std::array::from_fn(|c| a[c] + (b[c] - a[c]) * t)
}

impl Look {
    /// The backdrop's colour along a ray from `o` (inside the wall) in direction `d`: the
    /// nearer of the ground (tiles within the mat, plain floor outside) and the wall.
    pub fn backdrop(&self, o: DVec3, d: DVec3) -> [f64; 3] {
        // Wall: |(o + t d)_xz| = R, the root ahead of an origin inside the cylinder.
        let (a, b, c) = (
            d.x * d.x + d.z * d.z,
            o.x * d.x + o.z * d.z,
            o.x * o.x + o.z * o.z - self.wall_radius * self.wall_radius,
        );
        let t_wall = if a > 1e-12 {
            (-b + (b * b - a * c).max(0.0).sqrt()) / a
        } else {
            f64::INFINITY
        };
        let t_ground = if d.y < 0.0 { -o.y / d.y } else { f64::INFINITY };
        if t_ground < t_wall {
            let g = o + t_ground * d;
            if g.x.abs() <= self.mat_half && g.z.abs() <= self.mat_half {
                let (i, k) = (
                    (g.x / self.tile).floor() as i64,
                    (g.z / self.tile).floor() as i64,
                );
                if (i + k).rem_euclid(2) == 0 {
                    TILE_LIGHT
                } else {
                    TILE_DARK
                }
            } else {
                FLOOR
            }
        } else {
            let y = (o + t_wall * d).y;
            lerp(WALL_LOW, WALL_HIGH, (y / 2.5).clamp(0.0, 1.0))
        }
    }

    /// The backdrop alone (the background plate) at every sample of `cam`.
    pub fn plate(&self, cam: &Camera) -> Samples {
        let (sw, sh) = (
            (cam.width * self.ss) as usize,
            (cam.height * self.ss) as usize,
        );
        let mut rgb = Vec::with_capacity(sw * sh);
        for sy in 0..sh {
            for sx in 0..sw {
                let (o, d) = ray(cam, self.ss, sx, sy);
                rgb.push(self.backdrop(o, d));
            }
        }
        Samples {
            sw,
            sh,
            rgb,
            object: vec![false; sw * sh],
        }
    }

    /// The spheres of `centres` (m; radius `radius` m, colours `albedo` 0–255) in front of
    /// `plate` (the same camera's [`Self::plate`]). Spheres are visited in order and a sample
    /// keeps the nearest hit (the first of equal ones), so the result is deterministic.
    pub fn spheres(
        &self,
        cam: &Camera,
        plate: &Samples,
        centres: &[DVec3],
        radius: f64,
        albedo: &[[f64; 3]],
    ) -> Samples {
        let (sw, sh) = (plate.sw, plate.sh);
        let s = f64::from(self.ss);
        let mut depth = vec![f64::INFINITY; sw * sh];
        let mut hit: Vec<Option<u32>> = vec![None; sw * sh];
        for (i, c) in centres.iter().enumerate() {
            let Some((u, v, z)) = cam.project(*c) else {
                continue;
            };
            let dist = (*c - cam.centre_world).length();
            if z <= radius || dist <= radius {
                continue;
            }
            // A sphere's outline is an ellipse stretched away from the image centre by up to
            // 1/cos² of the off-axis angle; 1.5× the on-axis radius (+ a sample) bounds it
            // inside a 40–60° field of view.
            let rho = 1.5 * cam.fx.max(cam.fy) * radius / (dist * dist - radius * radius).sqrt()
                + 1.0 / s;
            let x0 = ((u - rho) * s).floor().max(0.0) as usize;
            let y0 = ((v - rho) * s).floor().max(0.0) as usize;
            let x1 = ((u + rho) * s).ceil().min(sw as f64) as usize;
            let y1 = ((v + rho) * s).ceil().min(sh as f64) as usize;
            for sy in y0..y1 {
                for sx in x0..x1 {
                    let (o, d) = ray(cam, self.ss, sx, sy);
                    let oc = o - *c;
                    let b = oc.dot(d);
                    let disc = b * b - (oc.length_squared() - radius * radius);
                    if disc < 0.0 {
                        continue;
                    }
                    let t = -b - disc.sqrt();
                    let k = sy * sw + sx;
                    if t > 0.0 && t < depth[k] {
                        depth[k] = t;
                        hit[k] = Some(i as u32);
                    }
                }
            }
        }
        let mut out = plate.clone();
        for sy in 0..sh {
            for sx in 0..sw {
                let k = sy * sw + sx;
                let Some(i) = hit[k] else { continue };
                let i = i as usize;
                let (o, d) = ray(cam, self.ss, sx, sy);
                let n = (o + depth[k] * d - centres[i]) / radius;
                let shade = self.ambient + self.diffuse * n.dot(self.to_light).max(0.0);
                out.rgb[k] = albedo[i].map(|a| a * shade);
                out.object[k] = true;
            }
        }
        out
    }

    /// The body of [`Surface`] in front of `plate` (the same camera's [`Self::plate`]),
    /// coloured by `albedo` of the rest position at each hit (0–255); the ground y = 0 hides
    /// what lies below it. Rows are traced in parallel; each sample depends on its ray only,
    /// so the result is the same for any thread count.
    pub fn surface(
        &self,
        cam: &Camera,
        plate: &Samples,
        surface: &Surface,
        albedo: impl Fn(DVec3) -> [f64; 3] + Sync,
    ) -> Samples {
        let sw = plate.sw;
        let mut out = plate.clone();
        out.rgb
            .par_chunks_mut(sw)
            .zip(out.object.par_chunks_mut(sw))
            .enumerate()
            .for_each(|(sy, (rgb, object))| {
                for sx in 0..sw {
                    let (o, d) = ray(cam, self.ss, sx, sy);
                    let t_ground = if d.y < 0.0 { -o.y / d.y } else { f64::INFINITY };
                    let Some((_, n, rest)) = surface.hit(o, d, t_ground) else {
                        continue;
                    };
                    let shade = self.ambient + self.diffuse * n.dot(self.to_light).max(0.0);
                    rgb[sx] = albedo(rest).map(|a| a * shade);
                    object[sx] = true;
                }
            });
        out
    }

    /// Pixels: each the mean of its `ss × ss` samples (colour rounded to 8 bits), and the
    /// object's coverage.
    pub fn resolve(&self, samples: &Samples) -> Frame {
        let ss = self.ss as usize;
        let (w, h) = (samples.sw / ss, samples.sh / ss);
        let n = (ss * ss) as f64;
        let mut rgb = Vec::with_capacity(w * h * 3);
        let mut alpha = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let mut sum = [0.0; 3];
                let mut covered = 0usize;
                for j in 0..ss {
                    for i in 0..ss {
                        let k = (y * ss + j) * samples.sw + x * ss + i;
                        for (s, v) in sum.iter_mut().zip(samples.rgb[k]) {
                            *s += v;
                        }
                        covered += usize::from(samples.object[k]);
                    }
                }
                rgb.extend(sum.map(|v| (v / n).round().clamp(0.0, 255.0) as u8));
                alpha.push((255.0 * covered as f64 / n).round() as u8);
            }
        }
        Frame { rgb, alpha }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    /// A camera at (0, 0.5, 2) looking down −z (OpenCV axes: x right, y down, z forward).
    fn camera() -> Camera {
        Camera {
            world_from_camera_rot: DMat3::from_cols(DVec3::X, -DVec3::Y, -DVec3::Z),
            centre_world: DVec3::new(0.0, 0.5, 2.0),
            fx: 50.0,
            fy: 50.0,
            cx: 20.0,
            cy: 20.0,
            width: 40,
            height: 40,
        }
    }

    /// One sphere in front of the camera covers a disc of the projected radius, lit from the
    /// light's side, and every pixel it does not touch equals the plate.
    #[test]
    fn a_sphere_covers_its_projected_disc_and_leaves_the_plate_elsewhere() {
        let look = Look {
            ss: 4,
            ..Look::default()
        };
        let cam = camera();
        let plate = look.plate(&cam);
        let centre = DVec3::new(0.0, 0.5, 0.0);
        let r = 0.2;
        let img = look.spheres(&cam, &plate, &[centre], r, &[[200.0, 100.0, 50.0]]);
        let frame = look.resolve(&img);
        let bare = look.resolve(&plate);
        // The outline's radius: f·r/sqrt(d² − r²) = 50·0.2/sqrt(4 − 0.04) px.
        let rho = 50.0 * r / (4.0f64 - r * r).sqrt();
        let covered: f64 = frame.alpha.iter().map(|a| f64::from(*a) / 255.0).sum();
        let area = std::f64::consts::PI * rho * rho;
        assert!((covered - area).abs() < 0.03 * area, "{covered} vs {area}");
        for y in 0..40usize {
            for x in 0..40usize {
                let p = y * 40 + x;
                let r2 = (x as f64 + 0.5 - 20.0).powi(2) + (y as f64 + 0.5 - 20.0).powi(2);
                if r2 > (rho + 1.5).powi(2) {
                    assert_eq!(frame.alpha[p], 0);
                    assert_eq!(frame.rgb[3 * p..3 * p + 3], bare.rgb[3 * p..3 * p + 3]);
                }
                if r2 < (rho - 1.5).powi(2) {
                    assert_eq!(frame.alpha[p], 255);
                }
            }
        }
        // The light comes from above (+y) and the right (+x): the upper right of the disc is
        // brighter than the lower left.
        let red = |x: usize, y: usize| frame.rgb[3 * (y * 40 + x)];
        assert!(
            red(22, 17) > red(17, 22) + 20,
            "{} {}",
            red(22, 17),
            red(17, 22)
        );
    }

    /// The nearer of two overlapping spheres is seen, whatever their order.
    #[test]
    fn the_nearer_sphere_hides_the_farther_one() {
        let look = Look::default();
        let cam = camera();
        let plate = look.plate(&cam);
        let near = DVec3::new(0.0, 0.5, 0.5);
        let far = DVec3::new(0.0, 0.5, -0.5);
        let colours = [[255.0, 0.0, 0.0], [0.0, 0.0, 255.0]];
        for order in [[near, far], [far, near]] {
            let albedo = if order[0] == near {
                colours
            } else {
                [colours[1], colours[0]]
            };
            let f = look.resolve(&look.spheres(&cam, &plate, &order, 0.1, &albedo));
            let p = 20 * 40 + 20;
            assert!(
                f.rgb[3 * p] > 0 && f.rgb[3 * p + 2] == 0,
                "{:?}",
                &f.rgb[3 * p..]
            );
        }
    }

    /// The backdrop: tiles alternate on the mat, plain floor beyond it, the wall above the
    /// horizon gets lighter towards the ground.
    #[test]
    fn backdrop_has_tiles_floor_and_wall() {
        let look = Look::default();
        let o = DVec3::new(0.0, 1.0, 0.0);
        let down = |x: f64, z: f64| look.backdrop(o, (DVec3::new(x, 0.0, z) - o).normalize());
        assert_eq!(down(0.05, 0.05), TILE_LIGHT);
        assert_eq!(down(0.15, 0.05), TILE_DARK);
        assert_eq!(down(-0.05, 0.05), TILE_DARK);
        assert_eq!(down(1.5, 0.0), FLOOR);
        let wall_low = look.backdrop(o, DVec3::new(1.0, -0.1, 0.0).normalize());
        let wall_high = look.backdrop(o, DVec3::new(1.0, 0.4, 0.0).normalize());
        assert!(wall_low[0] > wall_high[0], "{wall_low:?} {wall_high:?}");
    }
}
