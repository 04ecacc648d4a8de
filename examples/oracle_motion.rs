#![allow(deprecated)] // Device::ndarray
//! Issue 17's diagnostic: how good can the moving pixels get when the anchors follow their
//! objects *exactly*? Trains like `acags train` (same config, same trainer), but after every
//! step the anchors that lie inside a synthetic scene's moving object at frame 0 (the fast
//! sphere, the slow cube, the flying cube) get the object's true rigid path as their trajectory
//! knots, with their motion gate held open. Everything else (decoders, features, per-frame
//! features, offsets, scales, the other anchors' knots, densification, the rate term) trains as
//! usual. The run directory it writes is a normal run: it is compressed and evaluated with the
//! library's own `compress` and `eval`, so its `metrics.json` compares with any other run's.
//!
//! If the gap between moving and static pixels closes here, tracking is what limits the default
//! run; if it stays, the limit is in how the moving object's appearance is represented.
//!
//! With `--until STEP` the paths are imposed only before that step and training is free after it
//! (the knots then start on the true paths and the gradient keeps or loses them): whether
//! acquiring the object is what fails, or keeping it.
//!
//! `--gate own` divides the knots by each anchor's own motion gate instead of holding it open,
//! and `--gate-only` holds the object's gates open without touching its knots (both throughout,
//! or until `--until`): which of the two (paths held, gates held) carries `--until`'s gain. The
//! oracle runs on the default config, so since `train.moving_gates = "open"` became the default
//! the runs of docs/results.md (Follow-ups 16-18) need `--set train.moving_gates=off`.
//!
//! With `--at-openings` only the knots the curriculum opens at a step are set, right after that
//! step (its knot search and one Adam step used the search's placement), through each anchor's
//! own motion gate (not held), and training is free otherwise: placement when a knot opens as
//! good as the oracle's, the ceiling of any placement rule (`train.knot_search`,
//! `train.knot_consensus`). Like the oracle throughout, it writes the true displacement from the
//! anchor's canonical position into the knot and ignores the motion head's term and knot 0's
//! trained offset (both small beside the motion); an anchor whose gate is shut (below the 0.1
//! threshold) gets knots that do not act.
//!
//! With `model.trajectory_turn = "knots"` the paths include the object's turn since frame 0 in
//! the turn knots; `--free-turns` imposes the translations only and leaves the turns to the
//! gradient (whether the gradient finds the turn once the anchors are on the object's arcs).
//!
//! `cargo run --release --example oracle_motion -- OUT_DIR [--until STEP [--gate hold|own |
//! --gate-only] | --at-openings] [--free-turns] [--config FILE] [--set key=value]...`

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::{DMat3, DQuat, DVec3};

use acags::compute_backend::{BackendKind, host_device};
use acags::config::TrainConfig;
use acags::data::resolve::synthetic_preset;
use acags::data::synthetic::{
    FAST_SPHERE_RADIUS, FLOOR_Y, FLYING_CUBE_HALF, SLOW_CUBE_HALF, SyntheticSpec,
    fast_sphere_center, flying_cube_pose, slow_cube_pose,
};
use acags::host_math::sigmoid;
use acags::model::anchors::{Column, FACTOR_COUNT, MOTION_GATE};
use acags::run::{CHECKPOINT_FILE, CONFIG_FILE};
use acags::train::trainer::Trainer;

/// Margin around an object's frame-0 volume within which an anchor counts as the object's.
const MARGIN: f64 = 0.05;
/// The motion gate's logit held on the object's anchors: σ(4) = 0.982.
const GATE_LOGIT: f32 = 4.0;

#[derive(Clone, Copy)]
enum Shape {
    Sphere(f64),
    Cube(f64),
}

/// A rigid moving object: its shape and its pose (centre, cube → world rotation) over time.
struct Rigid {
    name: &'static str,
    shape: Shape,
    pose: Box<dyn Fn(f64) -> (DVec3, DMat3)>,
}

impl Rigid {
    fn contains_at_start(&self, p: DVec3) -> bool {
        // y points down: anchors this close to the floor are floor, not object.
        if p.y > FLOOR_Y - 0.02 {
            return false;
        }
        let (c, r) = (self.pose)(0.0);
        match self.shape {
            Shape::Sphere(radius) => (p - c).length() < radius + MARGIN,
            Shape::Cube(half) => {
                let local = r.transpose() * (p - c);
                local.abs().max_element() < half + MARGIN
            }
        }
    }

    /// Where the point that is at `p` at time 0 is at `time`.
    fn carry(&self, p: DVec3, time: f64) -> DVec3 {
        let (c0, r0) = (self.pose)(0.0);
        let (c, r) = (self.pose)(time);
        c + r * (r0.transpose() * (p - c0))
    }

    /// The object's turn from time 0 to `time`, as a rotation vector (axis × angle), taken on
    /// the side nearest `previous` (a turn past 180° continues rather than flipping).
    fn turn(&self, time: f64, previous: DVec3) -> DVec3 {
        let (_, r0) = (self.pose)(0.0);
        let (_, r) = (self.pose)(time);
        let v = DQuat::from_mat3(&(r * r0.transpose())).to_scaled_axis();
        let angle = v.length();
        if angle < 1e-9 {
            return v;
        }
        let other = v * (1.0 - std::f64::consts::TAU / angle);
        if (other - previous).length() < (v - previous).length() {
            other
        } else {
            v
        }
    }
}

fn moving_objects(spec: SyntheticSpec) -> Vec<Rigid> {
    let mut objects = vec![
        Rigid {
            name: "fast sphere",
            shape: Shape::Sphere(FAST_SPHERE_RADIUS),
            pose: Box::new(move |t| (fast_sphere_center(&spec, t), DMat3::IDENTITY)),
        },
        Rigid {
            name: "slow cube",
            shape: Shape::Cube(SLOW_CUBE_HALF),
            pose: Box::new(move |t| slow_cube_pose(&spec, t)),
        },
    ];
    if let Some(flight) = spec.flying_cube {
        objects.push(Rigid {
            name: "flying cube",
            shape: Shape::Cube(FLYING_CUBE_HALF),
            pose: Box::new(move |t| flying_cube_pose(&flight, t)),
        });
    }
    objects
}

/// What the oracle imposes on the anchors inside a moving object at frame 0 while it acts.
#[derive(Clone, Copy, PartialEq)]
enum Imposed {
    /// The true paths in every knot, through the rule's gates.
    Paths(GateRule),
    /// Only the motion gates, held open; the knots train freely.
    GatesOnly,
}

/// Whether the paths the oracle imposes include the objects' turns (a model trained with
/// `model.trajectory_turn = "knots"`) or leave the turn knots to the gradient (`--free-turns`).
#[derive(Clone, Copy, PartialEq)]
enum TurnRule {
    Imposed,
    Free,
}

/// Imposes `what` on the anchors inside a moving object at frame 0 (every knot).
/// Returns how many anchors each object holds.
fn impose(
    trainer: &mut Trainer,
    objects: &[Rigid],
    spec: &SyntheticSpec,
    what: Imposed,
    turns: TurnRule,
) -> Vec<usize> {
    let knots = trainer.model.anchors.dims.trajectory_knots();
    match what {
        Imposed::Paths(gates) => impose_knots(trainer, objects, spec, 0..knots, gates, turns),
        Imposed::GatesOnly => {
            impose_knots(trainer, objects, spec, 0..0, GateRule::Hold, TurnRule::Free)
        }
    }
}

/// Whether [`impose_knots`] holds the object's motion gates open or divides by their own.
#[derive(Clone, Copy, PartialEq)]
enum GateRule {
    Hold,
    Own,
}

/// The true paths into the knots in `only` (the rest untouched); with [`GateRule::Hold`] the
/// gates are held open even when `only` is empty.
fn impose_knots(
    trainer: &mut Trainer,
    objects: &[Rigid],
    spec: &SyntheticSpec,
    only: std::ops::Range<usize>,
    gates: GateRule,
    turn_rule: TurnRule,
) -> Vec<usize> {
    let dims = trainer.model.anchors.dims;
    let (spacing, knots) = (dims.trajectory_spacing, dims.trajectory_knots());
    let width = 3 * knots;
    let start = trainer.scene.frames.start;
    let last = trainer.scene.frames.count - 1;
    let time = |f: usize| (start + f) as f64 / (spec.frames.max(2) - 1) as f64;
    let gate = sigmoid(GATE_LOGIT) as f64;

    let set = &mut trainer.model.anchors;
    let mut trajectory = set.host(Column::Trajectory);
    // With trajectory turns, the object's true turn goes into the turn knots alike.
    let mut turns = match turn_rule {
        TurnRule::Imposed => set.host_if_present(Column::Turn),
        TurnRule::Free => None,
    };
    let mut factors = set.host(Column::Factors);
    let mut counts = vec![0; objects.len()];
    for (a, p) in set.positions.iter().enumerate() {
        let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let Some(o) = objects.iter().position(|o| o.contains_at_start(p)) else {
            continue;
        };
        counts[o] += 1;
        let object = &objects[o];
        let moved = |f: usize| object.carry(p, time(f)) - p;
        let gate_of_anchor = match gates {
            GateRule::Hold => gate,
            GateRule::Own => sigmoid(factors[a * FACTOR_COUNT + MOTION_GATE]).max(0.05) as f64,
        };
        let mut previous_turn = DVec3::ZERO;
        let turned = |f: usize, previous: DVec3| object.turn(time(f), previous);
        for (values, is_turn) in [(Some(&mut trajectory), false), (turns.as_mut(), true)] {
            let Some(values) = values else { continue };
            let row = &mut values[a * width..(a + 1) * width];
            let mut previous = DVec3::ZERO;
            for j in 0..knots {
                let frame = j * spacing;
                let mut at = |f: usize| {
                    if is_turn {
                        previous_turn = turned(f, previous_turn);
                        previous_turn
                    } else {
                        moved(f)
                    }
                };
                let knot = if frame <= last {
                    at(frame)
                } else {
                    // Past the clip: the knot that makes the last frame exact.
                    let w = (last - (frame - spacing)) as f64 / spacing as f64;
                    (at(last) - previous * (1.0 - w)) / w
                };
                previous = knot;
                if !only.contains(&j) {
                    continue;
                }
                let raw = knot / gate_of_anchor;
                row[j * 3..j * 3 + 3].copy_from_slice(&[raw.x as f32, raw.y as f32, raw.z as f32]);
            }
        }
        if gates == GateRule::Hold {
            factors[a * FACTOR_COUNT + MOTION_GATE] = GATE_LOGIT;
        }
    }
    set.set_host(Column::Trajectory, trajectory);
    if let Some(turns) = turns {
        set.set_host(Column::Turn, turns);
    }
    set.set_host(Column::Factors, factors);
    counts
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().context(
        "usage: oracle_motion OUT_DIR [--until STEP [--gate hold|own | --gate-only] | \
         --at-openings] [--free-turns] [--config FILE] [--set key=value]...",
    )?);
    let (mut config_file, mut overrides, mut until) = (None, Vec::new(), usize::MAX);
    // None: no --gate flag given (the paths through held gates).
    let (mut at_openings, mut what) = (false, None);
    let mut turns = TurnRule::Imposed;
    while let Some(flag) = args.next() {
        if flag == "--free-turns" {
            turns = TurnRule::Free;
            continue;
        }
        if flag == "--at-openings" {
            at_openings = true;
            until = 0;
            continue;
        }
        if flag == "--gate-only" {
            what = Some(Imposed::GatesOnly);
            continue;
        }
        let value = args
            .next()
            .with_context(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--config" => config_file = Some(PathBuf::from(value)),
            "--set" => overrides.push(value),
            "--until" => until = value.parse().context("--until takes a step number")?,
            "--gate" => {
                what = Some(Imposed::Paths(match value.as_str() {
                    "hold" => GateRule::Hold,
                    "own" => GateRule::Own,
                    other => bail!("--gate takes hold or own, not {other}"),
                }))
            }
            other => bail!("unknown flag {other}"),
        }
    }
    if at_openings && what.is_some() {
        bail!("--at-openings sets knots through each anchor's own gate: no --gate or --gate-only");
    }
    let what = what.unwrap_or(Imposed::Paths(GateRule::Hold));
    if out.join(CHECKPOINT_FILE).exists() {
        bail!("{} already holds a run", out.display());
    }
    let config = TrainConfig::load(config_file.as_deref(), &overrides)?;
    let Some(preset) = synthetic_preset(&config.data.dataset)? else {
        bail!(
            "the oracle knows the paths of synthetic scenes only, not {}",
            config.data.dataset
        );
    };
    if at_openings && config.train.frame_curriculum <= 0.0 {
        bail!(
            "--at-openings needs the temporal curriculum (train.frame_curriculum > 0) to open knots"
        );
    }
    if config.model.trajectory_spacing == 0 {
        bail!("the oracle writes trajectory knots: model.trajectory_spacing must be > 0");
    }
    let spec = preset.spec();
    let objects = moving_objects(spec);
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    std::fs::write(out.join(CONFIG_FILE), config.to_toml())?;

    let scene = config.data.load_scene()?;
    let mut trainer = Trainer::new(config.clone(), scene, host_device())?;
    let counts = if at_openings {
        Vec::new()
    } else {
        impose(&mut trainer, &objects, &spec, what, turns)
    };
    eprintln!(
        "oracle anchors at step 0: {}",
        objects
            .iter()
            .zip(&counts)
            .map(|(o, n)| format!("{} {n}", o.name))
            .collect::<Vec<_>>()
            .join(", ")
    );
    while !trainer.finished() {
        let report = trainer.step()?;
        let counts = if trainer.step < until {
            impose(&mut trainer, &objects, &spec, what, turns)
        } else if at_openings {
            // The knots this step opened, as the trainer's extend_trajectories decides them.
            let (step, d) = (report.step, trainer.model.anchors.dims);
            let opened = trainer.config.train.knots_opened(
                step,
                d.trajectory_spacing,
                d.frames,
                d.trajectory_knots(),
            );
            if !opened.is_empty() {
                let counts = impose_knots(
                    &mut trainer,
                    &objects,
                    &spec,
                    opened.clone(),
                    GateRule::Own,
                    turns,
                );
                eprintln!("step {step}: knots {opened:?} set on the objects' anchors {counts:?}");
                counts
            } else {
                Vec::new()
            }
        } else {
            Vec::new()
        };
        if report.step % 100 == 0 || trainer.finished() {
            eprintln!(
                "step {} loss {:.4} psnr {:.2} anchors {} gaussians {} oracle {:?} ({:.0} s)",
                report.step,
                report.loss,
                report.psnr,
                report.anchors,
                report.gaussians,
                counts,
                trainer.train_seconds
            );
        }
    }
    if let Some(p) = trainer.finish_training() {
        eprintln!("post-hoc: removed {} anchors", p.removed_anchors);
        if trainer.step < until {
            impose(&mut trainer, &objects, &spec, what, turns);
        }
    }
    trainer.save_checkpoint(&out.join(CHECKPOINT_FILE))?;
    acags::run::compress(&out, None, None)?;
    acags::run::eval(&out, BackendKind::Ndarray)?;
    Ok(())
}
