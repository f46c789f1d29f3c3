//! Rendering: the camera, relighting of the baked transfer under an environment, and the
//! empty-space-skipping ray march that turns both into an image. [`render_volume`] is the one entry
//! point once there is a density field, a transfer and a lighting.

pub(crate) mod camera;
pub(crate) mod film;
mod march;
pub mod motion;
pub mod relight;
pub mod sunlight;

use std::time::{Duration, Instant};

use glam::{DVec3, Vec3};

pub use camera::Camera;
pub use film::{band_rows, Background, Frame, Rows};
pub use march::{MarchSettings, MarchStats};

use march::Scene;
use relight::relight;

use crate::error::Result;
use crate::io::image::{ImageBuf, Layer};
use crate::light::Lighting;
use crate::transfer::Transfer;
use crate::volume::{DensityField, SparseGrid};
use sunlight::SunLight;

/// The camera flags of `render`: an explicit pose, or `position: None` for automatic framing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraSpec {
    pub position: Option<Vec3>,
    /// Defaults to the centre of the volume's bounding box.
    pub lookat: Option<Vec3>,
    pub up: Vec3,
    /// Horizontal field of view, degrees.
    pub fov_deg: f32,
    pub width: u32,
    pub height: u32,
}

impl CameraSpec {
    /// The camera for a volume whose active voxels span `bounds` in world space (`None`: empty).
    pub fn camera(&self, bounds: Option<(Vec3, Vec3)>) -> Result<Camera> {
        // An empty volume shows only the environment; frame a unit box at the origin.
        let (lo, hi) = bounds.unwrap_or((Vec3::splat(-0.5), Vec3::splat(0.5)));
        match self.position {
            Some(position) => Camera::look_at(
                position,
                self.lookat.unwrap_or(0.5 * (lo + hi)),
                self.up,
                self.fov_deg,
                self.width,
                self.height,
            ),
            // Framed from +Z, then turned where it stands toward the look-at point with the up
            // direction (by default the framing camera's own: the box's centre and +Y).
            None => {
                let framed = Camera::framing(lo, hi, self.width, self.height, self.fov_deg)?;
                Camera::look_at(
                    framed.position,
                    self.lookat.unwrap_or(0.5 * (lo + hi)),
                    self.up,
                    self.fov_deg,
                    self.width,
                    self.height,
                )
            }
        }
    }
}

/// Voxels whose density is below this fraction of the grid's maximum do not count when a camera
/// frames the volume: simulation caches carry wide active regions of near-zero density (a real
/// smoke frame whose visible smoke is a tenth of its active box was framed as a 60-pixel blob at
/// 1280×720), and 2 % of the peak keeps the faint edges a viewer can still see in the frame.
pub const FRAMING_DENSITY_FRACTION: f32 = 0.02;

/// World-space box of the voxel centres a camera should frame (any sign of scale): those with at
/// least [`FRAMING_DENSITY_FRACTION`] of the maximum density, or every active voxel when none is
/// positive; `None` when nothing is active.
pub fn framing_bounds(grid: &SparseGrid) -> Option<(Vec3, Vec3)> {
    let max = grid.value_stats()?.max;
    let (lo, hi) = if max > 0.0 {
        grid.bbox_above(FRAMING_DENSITY_FRACTION * max)?
    } else {
        grid.active_bbox()?
    };
    let a = grid.transform.index_to_world(lo.as_dvec3());
    let b = grid.transform.index_to_world(hi.as_dvec3());
    let (a, b): (DVec3, DVec3) = (a.min(b), a.max(b));
    Some((a.as_vec3(), b.as_vec3()))
}

/// Wall-clock time of each stage, for `--stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderReport {
    /// Projecting the light onto SH.
    pub project: Duration,
    pub relight: Duration,
    pub march: Duration,
}

/// The light of one render: the lighting, and the light of each of its suns on this volume (in
/// the order of `lighting.suns`).
pub struct Light<'a> {
    pub lighting: &'a Lighting,
    pub suns: &'a [&'a SunLight],
}

/// Relights `transfer` under `light` and hands `consume` the march of `field` as `camera` sees it,
/// row by row ([`Rows`]), with `background` behind the volume (`None`: alpha); `progress` counts
/// image tiles. The statistics and the march time are those of every row `consume` asked for.
#[allow(clippy::too_many_arguments)]
pub fn render_volume<R>(
    field: &DensityField,
    transfer: &Transfer,
    light: &Light,
    background: Option<Background>,
    camera: &Camera,
    settings: &MarchSettings,
    progress: &indicatif::ProgressBar,
    consume: impl FnOnce(&mut Rows) -> R,
) -> Result<(R, MarchStats, RenderReport)> {
    let Light { lighting, suns } = *light;
    let t = Instant::now();
    let env_coeffs = lighting.sh_coefficients(transfer.bands);
    let project = t.elapsed();
    let (radiance, relit) = relight(transfer, &env_coeffs)?;
    let t = Instant::now();
    let multiple = sunlight::multiple_radiance(
        suns.iter()
            .zip(&lighting.suns)
            .filter_map(|(light, sun)| light.multiple.as_ref().map(|m| (m, sun.irradiance))),
    );
    let source = (
        march::TransferRadiance::new(
            &transfer.layout,
            transfer.basis,
            &radiance,
            // Only the environment's light is shaped: without it the direct records are zero.
            transfer
                .shape
                .as_deref()
                .filter(|_| env_coeffs.iter().flatten().any(|&c| c != 0.0))
                .map(|s| march::Shaping {
                    visibility: &s.visibility,
                    fitted: &s.fitted,
                }),
        ),
        march::SunRadiance::new(
            suns.iter()
                .zip(&lighting.suns)
                .map(|(light, sun)| (&light.shadow, sun.irradiance)),
            multiple
                .as_ref()
                .map(|(layout, nodes)| (layout.as_ref(), nodes.as_slice())),
        ),
    );
    let relight_time = relit + t.elapsed();
    let scene = Scene::new(field, transfer.medium, &source, background);
    let (out, stats, march_time) = march::stream(&scene, camera, settings, progress, consume);
    let report = RenderReport {
        project,
        relight: relight_time,
        march: march_time,
    };
    Ok((out, stats, report))
}

impl Frame {
    /// The frame as an image to write: RGBA (premultiplied, as [`ImageBuf`] expects), plus, with
    /// `layers`, the `direct.{R,G,B}`, `indirect.{R,G,B}` and `depth.Z` layers, which EXR keeps
    /// and PNG ignores.
    pub fn into_image(self, layers: bool) -> ImageBuf {
        // The buffers move over as they are: the EXR writer reads interleaved channels in place.
        let rgb = &["R", "G", "B"];
        ImageBuf {
            width: self.width as usize,
            height: self.height as usize,
            rgba: self.rgba,
            layers: match layers {
                false => Vec::new(),
                true => vec![
                    Layer {
                        name: "direct",
                        channels: rgb,
                        values: self.direct.into_flattened(),
                    },
                    Layer {
                        name: "indirect",
                        channels: rgb,
                        values: self.indirect.into_flattened(),
                    },
                    Layer {
                        name: "depth",
                        channels: &["Z"],
                        values: self.depth,
                    },
                ],
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::env::Environment;
    use crate::light::sh::Window;
    use crate::transfer::{Coefficients, Medium, TransferLayout};
    use crate::volume::grid::TileLevel;
    use crate::volume::Transform;
    use glam::IVec3;

    #[test]
    fn camera_spec_frames_or_poses() {
        let (lo, hi) = (Vec3::new(0.0, 0.0, 0.0), Vec3::new(2.0, 4.0, 6.0));
        let bounds = Some((lo, hi));
        let spec = CameraSpec {
            position: None,
            lookat: None,
            up: Vec3::Y,
            fov_deg: 45.0,
            width: 64,
            height: 32,
        };
        let framed = spec.camera(bounds).unwrap();
        assert_eq!(framed, Camera::framing(lo, hi, 64, 32, 45.0).unwrap());
        let posed = CameraSpec {
            position: Some(Vec3::new(10.0, 2.0, 3.0)),
            ..spec
        }
        .camera(bounds)
        .unwrap();
        // Without --lookat the camera looks at the box centre.
        let (_, d) = posed.ray(32.0, 16.0);
        assert!((d - (Vec3::new(1.0, 2.0, 3.0) - posed.position).normalize()).length() < 1e-5);
        assert!(spec.camera(None).is_ok());
    }

    #[test]
    fn framing_bounds_handle_negative_scale() {
        let mut g = SparseGrid::new(
            Transform {
                scale: DVec3::new(0.5, -1.0, 2.0),
                translation: DVec3::new(1.0, 0.0, 0.0),
            },
            0.0,
        );
        assert_eq!(framing_bounds(&g), None);
        g.insert_tile(TileLevel::Block, IVec3::ZERO, 1.0);
        let (lo, hi) = framing_bounds(&g).unwrap();
        assert_eq!(lo, Vec3::new(1.0, -7.0, 0.0));
        assert_eq!(hi, Vec3::new(4.5, 0.0, 14.0));
    }

    #[test]
    fn framing_follows_the_density_not_faint_active_voxels() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        // A wide node tile of faint noise (1 % of the peak) around a dense 8³ block.
        g.insert_tile(TileLevel::Node, IVec3::new(-128, 0, 0), 0.01);
        g.insert_tile(TileLevel::Block, IVec3::new(16, 8, 0), 1.0);
        let (lo, hi) = framing_bounds(&g).unwrap();
        assert_eq!(
            (lo, hi),
            (Vec3::new(16.0, 8.0, 0.0), Vec3::new(23.0, 15.0, 7.0))
        );
        // With nothing positive the active box is framed.
        let mut zero = SparseGrid::new(Transform::default(), 0.0);
        zero.insert_tile(TileLevel::Block, IVec3::ZERO, 0.0);
        assert_eq!(framing_bounds(&zero), Some((Vec3::ZERO, Vec3::splat(7.0))));
    }

    #[test]
    fn render_volume_white_furnace_and_layers() {
        // A transfer of 1 from every direction (T₀ = √(4π)) split half direct, half multiply
        // scattered; albedo 1 and a constant environment c: every pixel is c (docs/model.md,
        // for this chain given an energy-conserving transfer), and the layers add up.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::ZERO, 1.0);
        let layout = TransferLayout::build(&g, 6);
        let sqrt_4pi = (4.0 * std::f32::consts::PI).sqrt();
        let n = layout.len() * 4;
        let dc =
            |v: f32| Coefficients::F32((0..n).map(|i| if i % 4 == 0 { v } else { 0.0 }).collect());
        let transfer = Transfer {
            layout,
            bands: 2,
            medium: Medium {
                sigma_t: 0.05,
                albedo: 1.0,
            },
            light: crate::transfer::TransferLight::Coefficients {
                t_ri: dc(0.5 * sqrt_4pi),
                f_ms: dc(0.5 * sqrt_4pi),
            },
            lattice: None,
            shape: None,
            basis: crate::transfer::Basis::Tent,
        };
        let c = [0.5f32, 1.0, 2.0];
        let lighting = Lighting {
            env: Environment::from_pixels(16, 8, vec![c; 128]).unwrap().0,
            rotation: 0.0,
            scale: 1.0,
            window: Window::None,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        let bg = film::each_direction(|_| c);
        let cam = Camera::framing(Vec3::ZERO, Vec3::splat(127.0), 24, 16, 45.0).unwrap();
        let field = DensityField::new(g);
        let (frame, stats, _) = render_volume(
            &field,
            &transfer,
            &Light {
                lighting: &lighting,
                suns: &[],
            },
            Some(&bg),
            &cam,
            &MarchSettings::default(),
            &indicatif::ProgressBar::hidden(),
            |rows| rows(0..16, true),
        )
        .unwrap();
        assert_eq!(stats.rays, 24 * 16);
        for px in &frame.rgba {
            for ch in 0..3 {
                assert!((px[ch] - c[ch]).abs() < 1e-4 * c[ch], "{px:?}");
            }
        }
        // The transfer splits evenly, so the layers agree wherever the volume is.
        let centre = 8 * 24 + 12;
        assert!(frame.direct[centre][0] > 0.1);
        for (d, i) in frame.direct.iter().zip(&frame.indirect) {
            assert!(
                (d[1] - i[1]).abs() <= 1e-5 * d[1].max(1e-3),
                "{d:?} vs {i:?}"
            );
        }
        let depth_at_centre = frame.depth[centre];
        assert!(depth_at_centre > 0.0);
        let image = frame.into_image(true);
        let names: Vec<(&str, &[&str])> =
            image.layers.iter().map(|l| (l.name, l.channels)).collect();
        let rgb: &[&str] = &["R", "G", "B"];
        assert_eq!(
            names,
            [("direct", rgb), ("indirect", rgb), ("depth", &["Z"][..])]
        );
        let (direct, indirect) = (&image.layers[0].values, &image.layers[1].values);
        for ch in centre * 3..centre * 3 + 3 {
            assert!(
                (direct[ch] - indirect[ch]).abs() <= 1e-5 * direct[ch],
                "channel {ch}"
            );
        }
        assert_eq!(image.layers[2].values[centre], depth_at_centre);
    }
}
