//! Bridges from the scene's types to the rasterizer's (`pipe-render`) borrowed views.

use super::camera::Camera;
use super::gaussians::Gaussians;

/// Near plane used for every render, metres.
pub const NEAR_M: f32 = 0.01;

/// The rasterizer's camera (`camera_from_world`, f32) for a scene camera.
pub fn render_camera(cam: &Camera) -> pipe_render::Camera<f32> {
    let r = cam.world_from_camera_rot.transpose(); // camera_from_world rotation
    let t = -(r * cam.centre_world);
    let rows = [r.row(0), r.row(1), r.row(2)];
    pipe_render::Camera {
        camera_from_world_rotation: rows.map(|row| [row.x as f32, row.y as f32, row.z as f32]),
        camera_from_world_translation: [t.x as f32, t.y as f32, t.z as f32],
        fx: cam.fx as f32,
        fy: cam.fy as f32,
        cx: cam.cx as f32,
        cy: cam.cy as f32,
        width: cam.width,
        height: cam.height,
        near: NEAR_M,
    }
}

/// A borrowed rasterizer view of the scene's Gaussians (log-scales, logits, SH).
pub fn render_gaussians(g: &Gaussians) -> pipe_render::Gaussians<'_, f32> {
    let (sh, rest) = g.sh.as_chunks::<3>();
    debug_assert!(rest.is_empty());
    pipe_render::Gaussians {
        means: &g.position,
        scales: pipe_render::Scales::Log(&g.log_scale),
        quats: &g.rotation,
        opacities: pipe_render::Opacities::Logit(&g.opacity_logit),
        colors: pipe_render::Colors::Sh {
            degree: u32::from(g.sh_degree),
            coeffs: sh,
        },
        deformation: None,
    }
}

/// [`render_gaussians`] with other SH coefficients `sh` (`[gaussian][coeff][channel]`, the
/// Gaussians' degree) in place of theirs: re-lit or refitted colours.
pub fn render_gaussians_sh<'a>(g: &'a Gaussians, sh: &'a [f32]) -> pipe_render::Gaussians<'a, f32> {
    debug_assert_eq!(sh.len(), g.sh.len());
    pipe_render::Gaussians {
        colors: pipe_render::Colors::Sh {
            degree: u32::from(g.sh_degree),
            coeffs: sh.as_chunks::<3>().0,
        },
        ..render_gaussians(g)
    }
}

/// Convert a rendered float image (`[H][W]` RGB in [0, 1]) to 8-bit RGB bytes.
pub fn to_rgb8(pixels: &[[f32; 3]]) -> Vec<u8> {
    pixels
        .iter()
        .flat_map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8))
        .collect()
}
