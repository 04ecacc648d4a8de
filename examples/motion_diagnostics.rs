#![allow(deprecated)] // Device::ndarray
//! Why a run does or does not reconstruct motion, from its checkpoint (docs/results.md, "Moving
//! objects"):
//!
//! 1. test metrics per frame (full image, moving and static pixels) as trained, with every anchor
//!    decoded (is culling dropping moved anchors?), and with every motion gate closed (how much
//!    of the dynamic quality the motion head carries);
//! 2. the motion the model learned: per anchor the largest gated translation over the GOP, and
//!    for synthetic scenes the anchors of the fast object at frame 0 against its true
//!    displacement at a few frames: their error split into the knots' part and the motion
//!    head's translation, and the knots' places into the object's pose (their best rigid motion
//!    against the truth) and each anchor's departure from it (docs/results.md, Follow-up 55).
//!
//! With `--decoded`, all of it for the run's decoded `scene.acags` (what ships; its features
//! are the rounded ones training ended on, so its motion can differ from the float32 model's).
//!
//! `cargo run --release --example motion_diagnostics -- RUN_DIR [--decoded] [FRAMES...]`

use anyhow::{Context, Result};
use burn::tensor::Device;

use acags::data::frames::FrameCache;
use acags::data::resolve::synthetic_preset;
use acags::data::scene::{Scene, ViewId};
use acags::data::synthetic::{
    FAST_SPHERE_RADIUS, FLYING_CUBE_HALF, PixelLabel, SyntheticSpec, fast_sphere_center,
    flying_cube_pose, object_labels, object_moves, object_names,
};
use acags::eval::config::EvalConfig;
use acags::eval::evaluate::{
    EvalSummary, Scoring, evaluate, evaluation_time, render_view, test_motion_masks,
};
use acags::host_math::sigmoid;
use acags::model::anchored::AnchoredModel;
use acags::model::anchors::{Column, FACTOR_COUNT, MOTION_GATE, host_values};
use acags::model::inputs::GATE_THRESHOLD;
use acags::model::view::Phase;
use acags::model::view::{AnchorCulling, decode_view, deformed_positions};

fn print_frames(label: &str, eval: &EvalSummary, frames: &[usize]) {
    let r = &eval.regions;
    println!(
        "{label:<28} full {:.2} dB | dynamic {} | static {} | max gap {}",
        eval.psnr,
        r.dynamic_psnr.map_or("–".into(), |v| format!("{v:.2}")),
        r.static_psnr.map_or("–".into(), |v| format!("{v:.2}")),
        r.max_dynamic_gap
            .map_or("–".into(), |(f, g)| format!("{g:.2} (#{f})"))
    );
    let line: Vec<String> = r
        .frames
        .iter()
        .filter(|f| frames.contains(&f.frame))
        .map(|f| {
            format!(
                "#{} {:.1}/{}",
                f.frame,
                f.psnr,
                f.dynamic_psnr.map_or("–".into(), |v| format!("{v:.1}"))
            )
        })
        .collect();
    println!("{:<28} frame full/dynamic: {}", "", line.join("  "));
}

fn percentile(sorted: &[f32], p: f64) -> f32 {
    if sorted.is_empty() {
        return f32::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// A point of the model as glam's.
fn at(v: [f32; 3]) -> glam::DVec3 {
    glam::DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64)
}

/// The angle of a turn, degrees (q and −q are the same turn: with w < 0 the angle would read
/// 360° − θ).
fn turn_degrees(q: glam::DQuat) -> f64 {
    let q = if q.w < 0.0 { -q } else { q };
    q.to_axis_angle().1.to_degrees()
}

/// The one rigid motion that best carries `from` to `to` (least squares) and each point's
/// departure from it, in `from`'s order.
fn best_rigid_motion(
    from: &[glam::Vec3],
    to: &[glam::Vec3],
) -> Option<(acags::train::rigid_fit::RigidMotion, Vec<f32>)> {
    let motion = acags::train::rigid_fit::RigidMotion::fit(from, to)?;
    let departures = from.iter().zip(to).map(|(&p, &q)| (q - motion.apply(p)).length()).collect();
    Some((motion, departures))
}

/// Per-member `values` (in `members`' order) split by birth, each sorted: frame 0's point cloud
/// (`born`, the checkpoint's `aac.created_at`, is 0) and the anchors born later (grown, seeded).
fn split_by_birth(members: &[usize], values: &[f32], born: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let of = |later: bool| {
        let mut v: Vec<f32> = members
            .iter()
            .zip(values)
            .filter(|&(&a, _)| (born[a] > 0.0) == later)
            .map(|(_, &d)| d)
            .collect();
        v.sort_by(f32::total_cmp);
        v
    };
    (of(false), of(true))
}

/// A knot row (3 floats per knot, a knot every `spacing` frames) at `frame`, linear between
/// knots as `model/view.rs` interpolates them.
fn knot_at(row: &[f32], spacing: usize, frame: usize) -> glam::DVec3 {
    let (knot, w) = (frame / spacing, (frame % spacing) as f64 / spacing as f64);
    let get = |j: usize| at([row[j * 3], row[j * 3 + 1], row[j * 3 + 2]]);
    if w > 0.0 {
        get(knot) * (1.0 - w) + get(knot + 1) * w
    } else {
        get(knot)
    }
}

/// The moving pixels of every test view split by the object the ground truth shows at each
/// (`synthetic::object_labels`): which object the dynamic region's error is, a moving one or a
/// static one that a moving object uncovers, shadows or passes in front of. Over all frames, then
/// per frame in `shown`.
#[allow(clippy::too_many_arguments)]
fn moving_error_by_object(
    model: &AnchoredModel,
    scene: &Scene,
    frames: &FrameCache,
    phase: Phase,
    eval: &EvalConfig,
    spec: &SyntheticSpec,
    time: &dyn Fn(usize) -> f64,
    shown: &[usize],
) -> Result<()> {
    let objects = object_names(spec);
    let moves = object_moves(spec);
    // Categories: an object, split for the static ones by the moving object whose shadow the
    // point lies in (a moving shadow changes a static surface's colour), and the sky.
    let mut names: Vec<String> = Vec::new();
    let mut category = |label: &PixelLabel| -> usize {
        let name = match (label.object, label.shadow_of) {
            (None, _) => "sky".to_string(),
            (Some(o), Some(s)) if moves[s as usize] && s != o => {
                format!(
                    "{}, in the {}'s shadow",
                    objects[o as usize], objects[s as usize]
                )
            }
            (Some(o), _) => objects[o as usize].to_string(),
        };
        names.iter().position(|n| *n == name).unwrap_or_else(|| {
            names.push(name);
            names.len() - 1
        })
    };
    let masks = test_motion_masks(scene, frames, &eval.motion_mask())?;
    // Per GOP frame and category: squared error averaged over channels, and the pixel count.
    let count = scene.frames.count;
    let mut sse: Vec<Vec<f64>> = vec![Vec::new(); count];
    let mut pixels: Vec<Vec<usize>> = vec![Vec::new(); count];
    for &camera in &scene.test_cameras {
        for f in 0..count {
            let view = ViewId {
                camera,
                frame: scene.frames.start + f,
            };
            let truth = frames.get(scene, view)?;
            let image = render_view(model, scene, view, phase)?.image_host();
            let labels = object_labels(spec, &scene.cameras[camera].camera, time(f));
            let mask = &masks[&view];
            for (p, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
                let c = category(&labels[p]);
                if sse[f].len() <= c {
                    sse[f].resize(c + 1, 0.0);
                    pixels[f].resize(c + 1, 0);
                }
                let error: f64 = (0..3)
                    .map(|k| (image[3 * p + k] - truth.rgb[3 * p + k]) as f64)
                    .map(|d| d * d)
                    .sum();
                sse[f][c] += error / 3.0;
                pixels[f][c] += 1;
            }
        }
    }
    for f in 0..count {
        sse[f].resize(names.len(), 0.0);
        pixels[f].resize(names.len(), 0);
    }
    let psnr = |sse: f64, n: usize| -10.0 * (sse / n as f64).log10();
    let total_sse: f64 = sse.iter().flatten().sum();
    let total_pixels: usize = pixels.iter().flatten().sum();
    println!(
        "moving pixels by the object the ground truth shows there (test views, all frames): {} \
         pixels, PSNR {:.2}",
        total_pixels,
        psnr(total_sse, total_pixels)
    );
    // Largest share of the error first.
    let mut rows: Vec<(&String, f64, usize)> = names
        .iter()
        .enumerate()
        .map(|(o, name)| {
            (
                name,
                sse.iter().map(|f| f[o]).sum::<f64>(),
                pixels.iter().map(|f| f[o]).sum::<usize>(),
            )
        })
        .filter(|&(_, _, n)| n > 0)
        .collect();
    rows.sort_by(|a, b| b.1.total_cmp(&a.1));
    for (name, e, n) in rows {
        println!(
            "  {name:<42} {:5.1} % of the pixels, {:5.1} % of the squared error, PSNR {:.2}",
            100.0 * n as f64 / total_pixels as f64,
            100.0 * e / total_sse,
            psnr(e, n)
        );
    }
    for &f in shown.iter().filter(|&&f| f < count) {
        let n: usize = pixels[f].iter().sum();
        let e: f64 = sse[f].iter().sum();
        let parts: Vec<String> = names
            .iter()
            .enumerate()
            .filter(|&(o, _)| pixels[f][o] > 0)
            .map(|(o, name)| {
                format!(
                    "{name} {} px {:.1} dB ({:.0} %)",
                    pixels[f][o],
                    psnr(sse[f][o], pixels[f][o]),
                    100.0 * sse[f][o] / e
                )
            })
            .collect();
        println!(
            "  frame {f:>2}: {n} px {:.2} dB: {}",
            psnr(e, n.max(1)),
            parts.join(", ")
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let decoded_file = args
        .iter()
        .position(|a| a == "--decoded")
        .map(|i| args.remove(i));
    let dir = std::path::PathBuf::from(
        args.first()
            .context("usage: motion_diagnostics RUN_DIR [--decoded] [FRAMES...]")?,
    );
    let mut frames: Vec<usize> = args[1..]
        .iter()
        .map(|a| a.parse().context("frames are numbers"))
        .collect::<Result<_>>()?;
    if frames.is_empty() {
        frames = vec![0, 5, 10, 20, 30];
    }
    let mut run = acags::run::open_run(&dir, Device::ndarray())?;
    // The step each anchor was born at (0: frame 0's point cloud; later: grown or seeded), from
    // the checkpoint's trainer state; its rows are the float model's, not the decoded file's
    // (which may drop anchors), so only without `--decoded`.
    let born: Option<Vec<f32>> = if decoded_file.is_none() {
        let path = dir.join(acags::run::CHECKPOINT_FILE);
        let (tensors, _) = acags::train::checkpoint::read_checkpoint(&path)?;
        Some(tensors.get("aac.created_at", &path)?.1.clone())
    } else {
        None
    };
    if decoded_file.is_some() {
        let file = dir.join(acags::codec::scene_file::SCENE_FILE);
        let decoded = acags::codec::scene_file::read_scene(&file, &run.device)?;
        run.trained.model = decoded.model;
        println!("model: decoded {}", file.display());
    }
    let trained = &run.trained;
    let phase = trained.phase();
    let cfg = &trained.config;
    let scene = &run.scene;
    let eval = |model: &AnchoredModel| {
        evaluate(
            model,
            scene,
            &run.frames,
            phase,
            &cfg.eval,
            Scoring::PixelOnly,
            None,
        )
    };

    println!(
        "run {} (step {}, culling {:?})",
        dir.display(),
        trained.step,
        trained.model.culling
    );
    print_frames("as trained", &eval(&trained.model)?, &frames);
    let mut all = trained.model.clone();
    all.culling = AnchorCulling::Off;
    print_frames("every anchor decoded", &eval(&all)?, &frames);
    let mut still = trained.model.clone();
    let mut factors = still.anchors.host(Column::Factors);
    for row in factors.chunks_exact_mut(FACTOR_COUNT) {
        row[MOTION_GATE] = -30.0;
    }
    still.anchors.set_host(Column::Factors, factors);
    print_frames("motion gates closed", &eval(&still)?, &frames);

    // The learned motion.
    let set = &trained.model.anchors;
    let tensors = set.untracked();
    let count = scene.frames.count;
    let moved: Vec<Vec<[f32; 3]>> = (0..count)
        .map(|f| {
            deformed_positions(
                set,
                &tensors,
                &trained.model.decoders,
                evaluation_time(scene, scene.frames.start + f, phase),
            )
        })
        .collect();
    let distance = |a: [f32; 3], b: [f32; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let mut largest: Vec<f32> = (0..set.len())
        .map(|a| {
            moved
                .iter()
                .map(|m| distance(m[a], set.positions[a]))
                .fold(0.0, f32::max)
        })
        .collect();
    let gates: Vec<f32> = set
        .host(Column::Factors)
        .chunks_exact(FACTOR_COUNT)
        .map(|r| sigmoid(r[MOTION_GATE]))
        .collect();
    let mut sorted_gates = gates.clone();
    sorted_gates.sort_by(f32::total_cmp);
    largest.sort_by(f32::total_cmp);
    println!(
        "anchors {}: largest translation over the GOP median {:.4}, p99 {:.3}, max {:.3}; \
         motion gate σ median {:.3}, p99 {:.3}, share ≥ 0.1: {:.1} %",
        set.len(),
        percentile(&largest, 0.5),
        percentile(&largest, 0.99),
        percentile(&largest, 1.0),
        percentile(&sorted_gates, 0.5),
        percentile(&sorted_gates, 0.99),
        100.0 * gates.iter().filter(|&&g| g >= 0.1).count() as f64 / gates.len().max(1) as f64
    );

    // The fast object of a synthetic scene: its frame-0 anchors against its true motion.
    let Some(preset) = synthetic_preset(&cfg.data.dataset)? else {
        return Ok(());
    };
    let spec = preset.spec();
    // The generator's clock: dataset frame / (its frames − 1), whatever GOP was trained.
    let time = |f: usize| (scene.frames.start + f) as f64 / (spec.frames.max(2) - 1) as f64;
    moving_error_by_object(
        &trained.model,
        scene,
        &run.frames,
        phase,
        &cfg.eval,
        &spec,
        &time,
        &frames,
    )?;
    // The object's pose (centre, body → world rotation); the sphere's rotation is not tracked.
    type Pose = Box<dyn Fn(f64) -> (glam::DVec3, glam::DMat3)>;
    let (name, radius, pose): (&str, f64, Pose) = match spec.flying_cube {
        Some(flight) => (
            "flying cube",
            FLYING_CUBE_HALF * 3f64.sqrt(),
            Box::new(move |t| flying_cube_pose(&flight, t)),
        ),
        None => (
            "fast sphere",
            FAST_SPHERE_RADIUS,
            Box::new(move |t| (fast_sphere_center(&spec, t), glam::DMat3::IDENTITY)),
        ),
    };
    let track = |t: f64| pose(t).0;
    let (c0, r0) = pose(time(0));
    // Where a point of the object at p at frame 0 is at frame f (rigid motion).
    let carried = |p: glam::DVec3, f: usize| {
        let (c, r) = pose(time(f));
        c + r * r0.transpose() * (p - c0)
    };
    // Angle of the turn from frame 0 to frame f, degrees.
    let true_turn =
        |f: usize| turn_degrees(glam::DQuat::from_mat3(&(pose(time(f)).1 * r0.transpose())));
    // Whether x is on the object at frame f, within `margin`: the cube in its body frame (not
    // the ball around it, which reaches the orange sphere behind it), the sphere by its radius.
    let on_object = |x: glam::DVec3, f: usize, margin: f64| {
        let (c, r) = pose(time(f));
        match spec.flying_cube {
            Some(_) => (r.transpose() * (x - c)).abs().max_element() < FLYING_CUBE_HALF + margin,
            None => (x - c).length() < radius + margin,
        }
    };
    // The trajectory turns, where the model has them.
    let turn_knots = set.host_if_present(Column::Turn);
    let (turn_width, spacing) = (set.dims.turn_width(), set.dims.trajectory_spacing.max(1));
    // And the trajectory knots, to split a member's place into its knots' part and the motion
    // head's translation (Follow-up 55: which of the two scatters the members).
    let path_knots = set.host_if_present(Column::Trajectory);
    let path_width = set.dims.trajectory_width();
    let members: Vec<usize> = (0..set.len())
        .filter(|&a| on_object(at(set.positions[a]), 0, 0.05))
        .collect();
    println!(
        "{name}: {} anchors on it at frame 0 (within {:.2} of its centre); motion gate σ median {:.3}",
        members.len(),
        radius + 0.05,
        {
            let mut g: Vec<f32> = members.iter().map(|&a| gates[a]).collect();
            g.sort_by(f32::total_cmp);
            percentile(&g, 0.5)
        }
    );
    for &f in &frames {
        if f >= count {
            continue;
        }
        let truth = track(time(f)) - c0;
        // Each anchor against where the rigid motion carries it (its own true displacement,
        // rotation included; the centre's for the sphere), as a vector (learned − carried).
        let error_vectors: Vec<glam::DVec3> = members
            .iter()
            .map(|&a| at(moved[f][a]) - carried(at(set.positions[a]), f))
            .collect();
        let sorted_lengths = |vectors: &mut dyn Iterator<Item = glam::DVec3>| -> Vec<f32> {
            let mut v: Vec<f32> = vectors.map(|e| e.length() as f32).collect();
            v.sort_by(f32::total_cmp);
            v
        };
        let errors = sorted_lengths(&mut error_vectors.iter().copied());
        // The members' mean error vector: a lag along the flight is a bias every member shares;
        // the spread around it is each anchor's own.
        let mean_error = error_vectors.iter().sum::<glam::DVec3>() / members.len().max(1) as f64;
        let flight = truth.normalize_or_zero();
        let spread = sorted_lengths(&mut error_vectors.iter().map(|&e| e - mean_error));
        let mean_learned = members.iter().fold(glam::DVec3::ZERO, |acc, &a| {
            acc + at(moved[f][a]) - at(set.positions[a])
        }) / members.len().max(1) as f64;
        // Who draws the object at this frame: spawned Gaussians (opacity > 0) inside its true
        // volume, and whose anchors they are.
        let when = evaluation_time(scene, scene.frames.start + f, phase);
        let all: Vec<u32> = (0..set.len() as u32).collect();
        let view = decode_view(set, &tensors, &trained.model.decoders, all, when);
        let means = host_values(&view.gaussians.means);
        let gates = host_values(&view.gaussians.gates);
        let opacity = host_values(&view.gaussians.opacities);
        let centre = track(time(f));
        // The turn the members' slots make, as in `spawn`: the motion head's rotation
        // normalize(0.1·gate·Δq + (1, 0, 0, 0)), then the trajectory's turn q(gate·r(f)) where
        // the knots turn; and how far that is from the cube's own turn.
        let motion = host_values(&view.decoded.motion);
        let activated = host_values(&view.gates);
        let true_rotation = glam::DQuat::from_mat3(&(pose(time(f)).1 * r0.transpose()));
        // Per member: its slots' turn and its distance from the true turn (degrees), and whether
        // its trajectory turns it (non-zero turn knots at f).
        struct MemberTurn {
            turn: f32,
            error: f32,
            by_trajectory: bool,
        }
        let turned: Vec<MemberTurn> = members
            .iter()
            .map(|&a| {
                let g = activated[a * FACTOR_COUNT + MOTION_GATE] as f64;
                let head = glam::DQuat::from_xyzw(
                    0.1 * g * motion[a * 7 + 4] as f64,
                    0.1 * g * motion[a * 7 + 5] as f64,
                    0.1 * g * motion[a * 7 + 6] as f64,
                    1.0 + 0.1 * g * motion[a * 7 + 3] as f64,
                )
                .normalize();
                let knots = turn_knots
                    .as_ref()
                    .map(|t| knot_at(&t[a * turn_width..(a + 1) * turn_width], spacing, f))
                    .unwrap_or(glam::DVec3::ZERO);
                let q = glam::DQuat::from_scaled_axis(knots * g) * head;
                MemberTurn {
                    turn: turn_degrees(q) as f32,
                    error: turn_degrees(true_rotation.inverse() * q) as f32,
                    by_trajectory: knots != glam::DVec3::ZERO,
                }
            })
            .collect();
        let sorted = |values: &mut dyn Iterator<Item = f32>| -> Vec<f32> {
            let mut v: Vec<f32> = values.collect();
            v.sort_by(f32::total_cmp);
            v
        };
        let turns = sorted(&mut turned.iter().map(|t| t.turn));
        let turn_errors = sorted(&mut turned.iter().map(|t| t.error));
        // Members whose trajectory turns them and the others: under a derived turn
        // (`"objects"`) the members outside the cube's group do not turn, and one median over
        // both halves reads neither. Their turn errors, and their places' (`error_vectors`).
        let split = |by_trajectory: bool| {
            let chosen = || {
                turned
                    .iter()
                    .zip(&error_vectors)
                    .filter(move |(t, _)| t.by_trajectory == by_trajectory)
            };
            (
                sorted(&mut chosen().map(|(t, _)| t.error)),
                sorted_lengths(&mut chosen().map(|(_, &e)| e)),
            )
        };
        let ((with_turn, place_with), (without_turn, place_without)) = (split(true), split(false));
        // The knots' part of each member's place (canonical + gate × knots at f, the motion
        // head's translation left out) against where the rigid motion carries it, and the head's
        // translation (gate × its output) on its own.
        let by_knots: Option<Vec<glam::DVec3>> = path_knots.as_ref().map(|knots| {
            members
                .iter()
                .map(|&a| {
                    let g = activated[a * FACTOR_COUNT + MOTION_GATE] as f64;
                    let along = knot_at(&knots[a * path_width..(a + 1) * path_width], spacing, f);
                    at(set.positions[a]) + along * g
                })
                .collect()
        });
        let k = set.dims.slots;
        let (mut inside, mut from_members, mut opacity_sum) = (0usize, 0usize, 0.0f32);
        let member_set: std::collections::HashSet<usize> = members.iter().copied().collect();
        let mut anchor_shift = Vec::new();
        for g in 0..gates.len() {
            if gates[g] <= 0.0 {
                continue;
            }
            let m = at([means[3 * g], means[3 * g + 1], means[3 * g + 2]]);
            if (m - centre).length() < radius + 0.05 {
                inside += 1;
                opacity_sum += opacity[g];
                let a = g / k;
                if member_set.contains(&a) {
                    from_members += 1;
                }
                let p = set.positions[a];
                anchor_shift.push(
                    (glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) - c0).length() as f32,
                );
            }
        }
        anchor_shift.sort_by(f32::total_cmp);
        println!(
            "  frame {f:>3}: {inside} Gaussians inside the object (mean opacity {:.2}), {from_members} of them from its frame-0 anchors; their anchors' distance from the frame-0 centre: median {:.2}",
            opacity_sum / inside.max(1) as f32,
            percentile(&anchor_shift, 0.5)
        );
        println!(
            "  frame {f:>3}: true displacement {:.2} ({:+.2}, {:+.2}, {:+.2}); learned mean ({:+.2}, {:+.2}, {:+.2}); error median {:.2} p90 {:.2}",
            truth.length(),
            truth.x,
            truth.y,
            truth.z,
            mean_learned.x,
            mean_learned.y,
            mean_learned.z,
            percentile(&errors, 0.5),
            percentile(&errors, 0.9)
        );
        println!(
            "  frame {f:>3}: members' mean error ({:+.2}, {:+.2}, {:+.2}), {:+.2} along the flight; around it median {:.2} p90 {:.2}",
            mean_error.x,
            mean_error.y,
            mean_error.z,
            mean_error.dot(flight),
            percentile(&spread, 0.5),
            percentile(&spread, 0.9)
        );
        if spec.flying_cube.is_some() {
            // For scale: the error the members would have if each moved exactly with the
            // centre's translation and did not turn.
            let mut translated_only: Vec<f32> = members
                .iter()
                .map(|&a| {
                    let p = at(set.positions[a]);
                    (p + truth - carried(p, f)).length() as f32
                })
                .collect();
            translated_only.sort_by(f32::total_cmp);
            println!(
                "  frame {f:>3}: true turn {:.0}°; the members' slots turn median {:.0}° (p10 {:.0}°, p90 {:.0}°), {:.0}° from the true turn (p90 {:.0}°); moved with the centre without turning, their error would be median {:.2} p90 {:.2}",
                true_turn(f),
                percentile(&turns, 0.5),
                percentile(&turns, 0.1),
                percentile(&turns, 0.9),
                percentile(&turn_errors, 0.5),
                percentile(&turn_errors, 0.9),
                percentile(&translated_only, 0.5),
                percentile(&translated_only, 0.9)
            );
            if let Some(knots_only) = &by_knots {
                let canonical = members.iter().map(|&a| at(set.positions[a]));
                let knot_errors: Vec<glam::DVec3> = canonical
                    .clone()
                    .zip(knots_only)
                    .map(|(p, &k)| k - carried(p, f))
                    .collect();
                let mean =
                    knot_errors.iter().sum::<glam::DVec3>() / knot_errors.len().max(1) as f64;
                let around = sorted_lengths(&mut knot_errors.iter().map(|&e| e - mean));
                let head = sorted(
                    &mut members
                        .iter()
                        .zip(knots_only)
                        .map(|(&a, &k)| (at(moved[f][a]) - k).length() as f32),
                );
                println!(
                    "  frame {f:>3}: by the knots alone (the motion head's translation left out): members' mean error ({:+.2}, {:+.2}, {:+.2}), around it median {:.2} p90 {:.2}; the head's translation median {:.3} p90 {:.3}",
                    mean.x,
                    mean.y,
                    mean.z,
                    percentile(&around, 0.5),
                    percentile(&around, 0.9),
                    percentile(&head, 0.5),
                    percentile(&head, 0.9)
                );
                // The knots' places split: the one rigid motion that fits them best (how far the
                // object's pose is off) and each member's departure from it (what no rigid
                // correction of the object can mend).
                let v = |p: glam::DVec3| glam::Vec3::new(p.x as f32, p.y as f32, p.z as f32);
                let from: Vec<glam::Vec3> = canonical.clone().map(v).collect();
                let to: Vec<glam::Vec3> = knots_only.iter().map(|&k| v(k)).collect();
                // Per member, in `members`' order (split by birth below).
                if let Some((best, departure)) = best_rigid_motion(&from, &to) {
                    let placed = |p: glam::DVec3| best.apply(v(p)).as_dvec3();
                    let pose_error = sorted(
                        &mut canonical
                            .clone()
                            .map(|p| (placed(p) - carried(p, f)).length() as f32),
                    );
                    let departures = sorted(&mut departure.iter().copied());
                    println!(
                        "  frame {f:>3}: the knots' best rigid motion turns {:.0}° ({:.0}° from the true turn), its places off the truth median {:.2} p90 {:.2}; the members' departures from it median {:.2} p90 {:.2}",
                        turn_degrees(best.rotation.as_dquat()),
                        turn_degrees(true_rotation.inverse() * best.rotation.as_dquat()),
                        percentile(&pose_error, 0.5),
                        percentile(&pose_error, 0.9),
                        percentile(&departures, 0.5),
                        percentile(&departures, 0.9)
                    );
                    // The same split over the members a fit turned alone (a member no fit moved
                    // pulls the least-squares motion off the others).
                    let (fitted_from, fitted_to): (Vec<glam::Vec3>, Vec<glam::Vec3>) = from
                        .iter()
                        .zip(&to)
                        .zip(&turned)
                        .filter(|(_, t)| t.by_trajectory)
                        .map(|((&p, &k), _)| (p, k))
                        .unzip();
                    if let Some((fit, fitted_departures)) =
                        best_rigid_motion(&fitted_from, &fitted_to)
                    {
                        let fitted_departures = sorted(&mut fitted_departures.into_iter());
                        let fitted_pose = sorted(&mut fitted_from.iter().map(|&p| {
                            (fit.apply(p).as_dvec3() - carried(p.as_dvec3(), f)).length() as f32
                        }));
                        println!(
                            "  frame {f:>3}: the {} members a fit turned alone: their knots' best rigid motion turns {:.0}° ({:.0}° from the true turn), places off the truth median {:.2} p90 {:.2}; departures median {:.2} p90 {:.2}",
                            fitted_from.len(),
                            turn_degrees(fit.rotation.as_dquat()),
                            turn_degrees(true_rotation.inverse() * fit.rotation.as_dquat()),
                            percentile(&fitted_pose, 0.5),
                            percentile(&fitted_pose, 0.9),
                            percentile(&fitted_departures, 0.5),
                            percentile(&fitted_departures, 0.9)
                        );
                    }
                    // The motion gate scales an anchor's whole displacement (canonical + gate ×
                    // knots), and each gate trains on its own after the opening that sized its
                    // knot change for the gate of then: members whose gates drift apart depart
                    // from their object's motion by (gate − gate') × knots. The departures again
                    // with every member's gate replaced by the members' median (what the drift
                    // of the gates apart accounts for).
                    if let Some(knots) = &path_knots {
                        let member_gates = sorted(
                            &mut members
                                .iter()
                                .map(|&a| activated[a * FACTOR_COUNT + MOTION_GATE]),
                        );
                        let common = percentile(&member_gates, 0.5) as f64;
                        let with_common: Vec<glam::Vec3> = members
                            .iter()
                            .map(|&a| {
                                let row = &knots[a * path_width..(a + 1) * path_width];
                                v(at(set.positions[a]) + knot_at(row, spacing, f) * common)
                            })
                            .collect();
                        if let Some((_, common_departures)) = best_rigid_motion(&from, &with_common)
                        {
                            let common_departures = sorted(&mut common_departures.into_iter());
                            println!(
                                "  frame {f:>3}: members' motion gates p10 {:.3} median {:.3} p90 {:.3}; with every member at the median gate, departures median {:.2} p90 {:.2}",
                                percentile(&member_gates, 0.1),
                                common,
                                percentile(&member_gates, 0.9),
                                percentile(&common_departures, 0.5),
                                percentile(&common_departures, 0.9)
                            );
                        }
                    }
                    // The departures by where the members came from: a grown anchor takes its
                    // parents' mean displacement, not the object's motion at its own place.
                    if let Some(born) = &born {
                        let (first, later) = split_by_birth(&members, &departure, born);
                        println!(
                            "  frame {f:>3}: departures of the {} members from frame 0's point cloud median {:.2} p90 {:.2}; of the {} born later (grown, seeded) median {:.2} p90 {:.2}",
                            first.len(),
                            percentile(&first, 0.5),
                            percentile(&first, 0.9),
                            later.len(),
                            percentile(&later, 0.5),
                            percentile(&later, 0.9)
                        );
                    }
                }
            }
            if turn_knots.is_some() {
                println!(
                    "  frame {f:>3}: {} of {} members turn by their trajectory, {:.0}° from the true turn (median; p90 {:.0}°); the others {:.0}° (p90 {:.0}°); their places' error median {:.2} / {:.2}",
                    with_turn.len(),
                    members.len(),
                    percentile(&with_turn, 0.5),
                    percentile(&with_turn, 0.9),
                    percentile(&without_turn, 0.5),
                    percentile(&without_turn, 0.9),
                    percentile(&place_with, 0.5),
                    percentile(&place_without, 0.5)
                );
                // The members no fit turned: on the cube itself, or static points within the
                // margin of its frame-0 box; and whether their gates let anything move them.
                let strays: Vec<usize> = members
                    .iter()
                    .zip(&turned)
                    .filter(|(_, t)| !t.by_trajectory)
                    .map(|(&a, _)| a)
                    .collect();
                let on_cube = strays
                    .iter()
                    .filter(|&&a| on_object(at(set.positions[a]), 0, 0.0))
                    .count();
                let stray_gates =
                    sorted(&mut strays.iter().map(|&a| activated[a * FACTOR_COUNT + MOTION_GATE]));
                println!(
                    "  frame {f:>3}: of the {} members no fit turned, {on_cube} lie on the cube itself at frame 0 (the others within the margin outside it); their motion gates median {:.3}, {} below the gate threshold",
                    strays.len(),
                    percentile(&stray_gates, 0.5),
                    stray_gates.iter().filter(|&&g| g < GATE_THRESHOLD).count()
                );
            }
        }
    }
    // Interval by interval (each knot's opening fits the object's motion over one interval): how
    // far the members' places at a knot depart from the one rigid motion that best carries their
    // places at the knot before, by the knots alone and in full (the motion head's translation
    // included: the fit moves the full places, then writes into the knot what leaves the head's
    // translation at the new frame in place). A departure that grows by a little on every member
    // at every interval is a drift; one carried by a few members is those a fit left out.
    if let (Some(_), Some(knots)) = (spec.flying_cube, &path_knots) {
        let knots_only = |f: usize| -> Vec<glam::Vec3> {
            members
                .iter()
                .map(|&a| {
                    let row = &knots[a * path_width..(a + 1) * path_width];
                    let p = at(set.positions[a]) + knot_at(row, spacing, f) * gates[a] as f64;
                    glam::Vec3::new(p.x as f32, p.y as f32, p.z as f32)
                })
                .collect()
        };
        let full = |f: usize| -> Vec<glam::Vec3> {
            members.iter().map(|&a| glam::Vec3::from_array(moved[f][a])).collect()
        };
        let interval = |from: &[glam::Vec3], to: &[glam::Vec3]| {
            best_rigid_motion(from, to)
                .map(|(fit, departures)| (turn_degrees(fit.rotation.as_dquat()), departures))
        };
        let sorted = |values: &mut dyn Iterator<Item = f32>| -> Vec<f32> {
            let mut v: Vec<f32> = values.collect();
            v.sort_by(f32::total_cmp);
            v
        };
        // Each knot's frame (the last knot's is the clip's last frame).
        let mut knot_frames: Vec<usize> = Vec::new();
        for j in 0.. {
            let f = (j * spacing).min(count - 1);
            if knot_frames.last() == Some(&f) {
                break;
            }
            knot_frames.push(f);
        }
        for pair in knot_frames.windows(2) {
            let (f0, f1) = (pair[0], pair[1]);
            let (Some((turn_k, by_knots)), Some((turn_f, in_full))) = (
                interval(&knots_only(f0), &knots_only(f1)),
                interval(&full(f0), &full(f1)),
            ) else {
                continue;
            };
            // By birth (float model only): frame 0's point cloud, and the anchors born later
            // (grown, seeded), which took their knots from others rather than from the fits.
            let by_birth = born.as_ref().map(|born| {
                let (first, later) = split_by_birth(&members, &by_knots, born);
                format!(
                    "; by the knots, point cloud median {:.3} ({}), born later {:.3} ({})",
                    percentile(&first, 0.5),
                    first.len(),
                    percentile(&later, 0.5),
                    later.len()
                )
            });
            let (by_knots, in_full) = (sorted(&mut by_knots.into_iter()), sorted(&mut in_full.into_iter()));
            let over = |r: &[f32], limit: f32| r.iter().filter(|&&v| v > limit).count();
            println!(
                "  interval {f0:>2} -> {f1:>2} ({} members): by the knots, best rigid turn {turn_k:.0}°, departures median {:.3} p90 {:.3}, {} over 0.05; in full, turn {turn_f:.0}°, departures median {:.3} p90 {:.3}, {} over 0.05{}",
                members.len(),
                percentile(&by_knots, 0.5),
                percentile(&by_knots, 0.9),
                over(&by_knots, 0.05),
                percentile(&in_full, 0.5),
                percentile(&in_full, 0.9),
                over(&in_full, 0.05),
                by_birth.unwrap_or_default()
            );
        }
    }
    // Tracking from any frame, not only from frame 0 (an object that enters later, as
    // large-motion's sphere, has no frame-0 anchors): the anchors inside the object at frame f
    // (where the model puts them) against where its motion carries them by frame f + 4, one
    // knot interval later.
    // (Follow-up 19's margins: the cube's 0.05 as for its members, none for the sphere.)
    let margin = if spec.flying_cube.is_some() {
        0.05
    } else {
        0.0
    };
    let inside = |x: glam::DVec3, f: usize| on_object(x, f, margin);
    // The pruning gates of those anchors (a closed one, σ < GATE_THRESHOLD, is pruned in
    // training and dropped by the writer; it shrinks the anchor's Gaussians before that).
    let pruning_gates: Vec<f32> = set
        .host(Column::Factors)
        .chunks_exact(FACTOR_COUNT)
        .map(|f| sigmoid(f[3]))
        .collect();
    for &f in &frames {
        let g = f + 4;
        if g >= count {
            continue;
        }
        let (cf, rf) = pose(time(f));
        let (cg, rg) = pose(time(g));
        let inside_f: Vec<usize> = (0..set.len())
            .filter(|&a| inside(at(moved[f][a]), f))
            .collect();
        let mut errors: Vec<f32> = inside_f
            .iter()
            .map(|&a| {
                let expected = cg + rg * rf.transpose() * (at(moved[f][a]) - cf);
                (at(moved[g][a]) - expected).length() as f32
            })
            .collect();
        errors.sort_by(f32::total_cmp);
        let mut gates: Vec<f32> = inside_f.iter().map(|&a| pruning_gates[a]).collect();
        gates.sort_by(f32::total_cmp);
        let closed = gates.iter().filter(|&&v| v < GATE_THRESHOLD).count();
        let still_inside = inside_f
            .iter()
            .filter(|&&a| inside(at(moved[g][a]), g))
            .count();
        println!(
            "  frames {f:>2} -> {g:>2}: {} anchors inside at {f}, {still_inside} of them inside at {g}; error against the object's motion median {:.2} p90 {:.2} (it moves {:.2}); pruning gate σ p10 {:.2} median {:.2}, {closed} closed (< 0.1)",
            inside_f.len(),
            percentile(&errors, 0.5),
            percentile(&errors, 0.9),
            (cg - cf).length(),
            percentile(&gates, 0.1),
            percentile(&gates, 0.5),
        );
    }
    Ok(())
}
