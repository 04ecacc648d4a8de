//! A moving object's rigid motion refined against the rendered model (`train.rigid_fit =
//! "rendered"`; our addition, not in GIFStream or ACA-GS).
//!
//! Why: the rigid fit ([`crate::train::rigid_fit`]) scores a motion by probing the training
//! images at its anchors' places, one colour per anchor and camera. On `synthetic:crossing` it
//! finds mostly 9-12° of the flying cube's 18° per knot interval (docs/results.md, Follow-ups 46
//! and 50): a probe sees through to whatever is in front of an anchor, and an anchor placed off
//! the surface agrees with several depths. Exact placement when a knot opens, held after it, is
//! worth +1.2 dB on the moving pixels over today's fit (Follow-up 50's oracle): the motion's
//! precision is the lever.
//!
//! How (analysis by synthesis): the object's Gaussians as the model draws them at the previous
//! knot's frame (trained on that frame's images; the template), moved by a candidate motion
//! (means and orientations), are drawn with every other Gaussian of the model at the new knot's
//! frame into each training camera, on a crop around the object, and compared with that frame's
//! training images (mean absolute difference). Occlusion, the object's silhouette and every pixel
//! of its texture count, not a colour per anchor. The new frame's images are not yet trained on,
//! so the fitted motion cannot certify itself (the lock seen when the anchors' own paths set the
//! motion, Follow-up 50). The search starts from the probe fit's motion ([`refine_motion`]).

use crate::data::frames::Frame;
use crate::model::anchored::BACKGROUND;
use crate::raster::RasterCamera;
use crate::raster::cpu::{GaussianArrays, ProjectionCamera, forward, is_visible, project_all};
use crate::train::knot_search::project;
use crate::train::rigid_fit::RigidMotion;
use glam::{Quat, Vec3};
use rayon::prelude::*;

/// Pixels added on each side of the object's projected extent (its places before and at the
/// start motion) to make a camera's crop: room for the refinement to move it and for the
/// Gaussians' footprints beyond their centres.
const CROP_PAD: f32 = 12.0;

/// One training camera's part of the score: a crop around the object, what the rest of the
/// model draws into it, and the training image there.
struct CropView {
    camera: RasterCamera,
    /// The Gaussians of everything else that reach the crop.
    others: GaussianArrays,
    /// [h, w, 3] the training image of the new frame on the crop.
    target: Vec<f32>,
}

/// The rendered score of an object's rigid motion between two frames.
pub struct RenderedScore {
    /// The object's Gaussians at the previous frame.
    template: GaussianArrays,
    views: Vec<CropView>,
}

impl RenderedScore {
    /// `template`: the object's Gaussians at the previous frame; `others`: every other Gaussian
    /// at the new frame; `rig` and `targets`: the training cameras and their images of the new
    /// frame; `start`: the motion the search starts from (with the template's place, it bounds
    /// each camera's crop). Cameras that see none of the object are left out.
    pub fn new(
        template: GaussianArrays,
        others: &GaussianArrays,
        rig: &[RasterCamera],
        targets: &[&Frame],
        start: &RigidMotion,
    ) -> Self {
        assert_eq!(rig.len(), targets.len(), "one image per camera");
        let points: Vec<Vec3> = template
            .means
            .chunks_exact(3)
            .map(|m| Vec3::from_slice(m))
            .collect();
        let views = rig
            .par_iter()
            .zip(targets)
            .filter_map(|(camera, image)| {
                let crop = crop_around(camera, &points, start)?;
                let projection = ProjectionCamera::new(&crop.camera);
                let reach = project_all(&others.slices(), &projection);
                let others = select(others, |i| is_visible(&reach[i]));
                let target = crop.cut(image);
                Some(CropView {
                    camera: crop.camera,
                    others,
                    target,
                })
            })
            .collect();
        Self { template, views }
    }

    /// Cameras that see the object.
    pub fn cameras(&self) -> usize {
        self.views.len()
    }

    /// The mean absolute colour difference over every crop's pixels between the model drawn with
    /// the object moved by `motion` and the training images; `None` when no camera sees it.
    pub fn score(&self, motion: &RigidMotion) -> Option<f32> {
        if self.views.is_empty() {
            return None;
        }
        let moved = moved(&self.template, motion);
        let (sum, count) = self
            .views
            .par_iter()
            .map(|view| {
                let drawn = concatenated(&moved, &view.others);
                let Ok(state) = forward(&drawn.slices(), &view.camera, BACKGROUND) else {
                    return (0.0f64, 0usize);
                };
                let image = &state.composite.image_alpha;
                let sum: f64 = view
                    .target
                    .chunks_exact(3)
                    .zip(image.chunks_exact(4))
                    .map(|(t, r)| {
                        ((t[0] - r[0]).abs() + (t[1] - r[1]).abs() + (t[2] - r[2]).abs()) as f64
                    })
                    .sum();
                (sum, view.target.len())
            })
            .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        (count > 0).then(|| (sum / count as f64) as f32)
    }

    /// The score of `refined` (which scores `at`) turned further by each of `extra_degrees`
    /// about its own axis, as "+d: difference" entries: whether a longer turn scores better
    /// (a search that stopped short) or worse (a score that prefers the shorter turn;
    /// docs/results.md, Follow-up 52). `None` for a motion that does not turn.
    pub fn turn_profile(
        &self,
        refined: &RigidMotion,
        at: f32,
        extra_degrees: &[f32],
    ) -> Option<String> {
        let (axis, angle) = refined.rotation.to_axis_angle();
        (angle > 1e-3).then(|| {
            extra_degrees
                .iter()
                .map(
                    |&d| match self.score(&refined.turned(axis, d.to_radians())) {
                        Some(s) => format!("{d:+.0}: {:+.5}", s - at),
                        None => format!("{d:+.0}: -"),
                    },
                )
                .collect::<Vec<_>>()
                .join(", ")
        })
    }
}

/// A camera cropped to a pixel rectangle, and where the rectangle lies in the full image.
struct Crop {
    camera: RasterCamera,
    x0: u32,
    y0: u32,
}

impl Crop {
    fn cut(&self, image: &Frame) -> Vec<f32> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let full = image.width as usize;
        let mut out = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            let row = (self.y0 as usize + y) * full + self.x0 as usize;
            out.extend_from_slice(&image.rgb[row * 3..(row + w) * 3]);
        }
        out
    }
}

/// The crop of `camera` around `points` before and after `start`, padded by [`CROP_PAD`];
/// `None` when none of them projects into the image.
fn crop_around(camera: &RasterCamera, points: &[Vec3], start: &RigidMotion) -> Option<Crop> {
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    let (w, h) = (camera.width as f32, camera.height as f32);
    let mut inside = false;
    for p in points.iter().flat_map(|&p| [p, start.apply(p)]) {
        let Some(xy) = project(camera, p.to_array()) else {
            continue;
        };
        inside |= xy[0] >= 0.0 && xy[0] < w && xy[1] >= 0.0 && xy[1] < h;
        for i in 0..2 {
            lo[i] = lo[i].min(xy[i]);
            hi[i] = hi[i].max(xy[i]);
        }
    }
    if !inside {
        return None;
    }
    let x0 = (lo[0] - CROP_PAD).floor().clamp(0.0, w - 1.0) as u32;
    let y0 = (lo[1] - CROP_PAD).floor().clamp(0.0, h - 1.0) as u32;
    let x1 = (hi[0] + CROP_PAD).ceil().clamp(1.0, w) as u32;
    let y1 = (hi[1] + CROP_PAD).ceil().clamp(1.0, h) as u32;
    (x1 > x0 && y1 > y0).then(|| Crop {
        camera: RasterCamera {
            width: x1 - x0,
            height: y1 - y0,
            cx: camera.cx - x0 as f32,
            cy: camera.cy - y0 as f32,
            ..camera.clone()
        },
        x0,
        y0,
    })
}

/// The template moved rigidly: each mean by `motion`, each orientation turned by its rotation.
fn moved(template: &GaussianArrays, motion: &RigidMotion) -> GaussianArrays {
    let mut out = template.clone();
    for (m, q) in out
        .means
        .chunks_exact_mut(3)
        .zip(out.quats.chunks_exact_mut(4))
    {
        m.copy_from_slice(&motion.apply(Vec3::from_slice(m)).to_array());
        // (w, x, y, z) in the rasterizer's layout.
        let turned = motion.rotation * Quat::from_xyzw(q[1], q[2], q[3], q[0]);
        q.copy_from_slice(&[turned.w, turned.x, turned.y, turned.z]);
    }
    out
}

/// The rows of `arrays` that `keep` selects.
pub fn select(arrays: &GaussianArrays, keep: impl Fn(usize) -> bool) -> GaussianArrays {
    let mut out = GaussianArrays::default();
    for i in (0..arrays.len()).filter(|&i| keep(i)) {
        out.means.extend_from_slice(&arrays.means[3 * i..3 * i + 3]);
        out.quats.extend_from_slice(&arrays.quats[4 * i..4 * i + 4]);
        out.scales
            .extend_from_slice(&arrays.scales[3 * i..3 * i + 3]);
        out.opacities.push(arrays.opacities[i]);
        out.gates.push(arrays.gates[i]);
        out.colors
            .extend_from_slice(&arrays.colors[3 * i..3 * i + 3]);
    }
    out
}

fn concatenated(a: &GaussianArrays, b: &GaussianArrays) -> GaussianArrays {
    let join = |x: &[f32], y: &[f32]| [x, y].concat();
    GaussianArrays {
        means: join(&a.means, &b.means),
        quats: join(&a.quats, &b.quats),
        scales: join(&a.scales, &b.scales),
        opacities: join(&a.opacities, &b.opacities),
        gates: join(&a.gates, &b.gates),
        colors: join(&a.colors, &b.colors),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::rotations::angle_of;
    use crate::train::knot_search::tests::rig;
    use crate::train::rigid_fit::refine_motion;

    /// A cube of side 0.8 at `centre` whose faces are a checker of small Gaussians of four
    /// colours (a turn shows as colours moving), on a grey wall behind it.
    fn textured_cube(centre: Vec3) -> GaussianArrays {
        let mut g = GaussianArrays::default();
        let palette = [
            [0.9, 0.1, 0.1],
            [0.1, 0.8, 0.2],
            [0.1, 0.2, 0.9],
            [0.9, 0.9, 0.2],
        ];
        let n = 8;
        for face in 0..6 {
            let (axis, sign) = (face / 2, if face % 2 == 0 { -1.0 } else { 1.0 });
            for i in 0..n {
                for j in 0..n {
                    let (u, v) = (
                        (i as f32 + 0.5) / n as f32 - 0.5,
                        (j as f32 + 0.5) / n as f32 - 0.5,
                    );
                    let mut p = [0.0f32; 3];
                    p[axis] = 0.5 * sign;
                    p[(axis + 1) % 3] = u;
                    p[(axis + 2) % 3] = v;
                    let p = centre + 0.8 * Vec3::from_array(p);
                    g.means.extend_from_slice(&p.to_array());
                    g.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
                    g.scales.extend_from_slice(&[0.05, 0.05, 0.05]);
                    g.opacities.push(0.95);
                    g.gates.push(1.0);
                    g.colors
                        .extend_from_slice(&palette[(i / 2 + 2 * (j / 2) + face) % 4]);
                }
            }
        }
        g
    }

    fn render(g: &GaussianArrays, camera: &RasterCamera) -> Frame {
        let state = forward(&g.slices(), camera, BACKGROUND).unwrap();
        Frame {
            width: camera.width,
            height: camera.height,
            rgb: state
                .composite
                .image_alpha
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect(),
        }
    }

    /// The cube drawn at frame 0, and at frame 1 moved by a known motion (a turn of 18° about a
    /// tilted axis and a shift of 0.3): from a start 8° and 0.08 off (what the probe fit leaves,
    /// Follow-up 50), the refinement finds the motion within 1.5° and 0.02.
    #[test]
    fn the_rendered_score_finds_a_turning_objects_motion() {
        let rig = rig();
        let centre = Vec3::new(0.0, -0.2, 0.0);
        let template = textured_cube(centre);
        let truth = RigidMotion {
            rotation: Quat::from_axis_angle(
                Vec3::new(0.3, 1.0, 0.2).normalize(),
                18f32.to_radians(),
            ),
            centre,
            translation: Vec3::new(0.3, 0.0, -0.1),
        };
        let wall = {
            let mut w = textured_cube(Vec3::new(0.0, 0.3, 0.0));
            // Flattened into a floor slab under the cube (y is up in this rig), grey: something
            // else in the crops.
            for m in w.means.chunks_exact_mut(3) {
                m[1] = -0.75 + 0.05 * m[1];
            }
            for c in w.colors.chunks_exact_mut(3) {
                c.copy_from_slice(&[0.5, 0.5, 0.5]);
            }
            w
        };
        let scene = concatenated(&moved(&template, &truth), &wall);
        let targets: Vec<Frame> = rig.iter().map(|c| render(&scene, c)).collect();
        let refs: Vec<&Frame> = targets.iter().collect();
        let start = RigidMotion {
            rotation: Quat::from_axis_angle(
                Vec3::new(0.3, 1.0, 0.2).normalize(),
                10f32.to_radians(),
            ),
            translation: truth.translation + Vec3::new(0.06, 0.0, 0.05),
            ..truth
        };
        let score = RenderedScore::new(template, &wall, &rig, &refs, &start);
        assert_eq!(score.cameras(), rig.len(), "every camera sees the cube");
        let at = |m: &RigidMotion| score.score(m).unwrap();
        assert!(
            at(&truth) < 1e-4,
            "the truth draws the images: {}",
            at(&truth)
        );
        assert!(
            at(&start) > 0.01,
            "the start is visibly off: {}",
            at(&start)
        );
        let (found, value) = refine_motion(|m| score.score(m), &[start], 0.05, 0.04).unwrap();
        let turn_error = angle_of(found.rotation * truth.rotation.inverse()).to_degrees();
        let shift_error = (found.apply(centre) - truth.apply(centre)).length();
        assert!(
            turn_error < 1.5 && shift_error < 0.02,
            "found {:.2} deg and {shift_error:.3} off the truth (score {value:.4})",
            turn_error
        );
    }

    /// Cameras that do not see the object are left out, and with none the score is `None`.
    #[test]
    fn an_object_no_camera_sees_has_no_score() {
        let rig = rig();
        let far = textured_cube(Vec3::new(0.0, 0.0, 0.0));
        let behind_all = moved(
            &far,
            &RigidMotion {
                translation: Vec3::new(0.0, -40.0, 0.0),
                ..RigidMotion::identity(Vec3::ZERO)
            },
        );
        let frames: Vec<Frame> = rig.iter().map(|c| render(&far, c)).collect();
        let refs: Vec<&Frame> = frames.iter().collect();
        let score = RenderedScore::new(
            behind_all,
            &GaussianArrays::default(),
            &rig,
            &refs,
            &RigidMotion::identity(Vec3::ZERO),
        );
        assert_eq!(score.cameras(), 0);
        assert_eq!(score.score(&RigidMotion::identity(Vec3::ZERO)), None);
    }
}
