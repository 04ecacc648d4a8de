//! Re-acquiring lost objects when a trajectory knot opens (`train.knot_search`; not in GIFStream
//! or ACA-GS, see `model/view.rs` on anchor trajectories).
//!
//! Why: a knot gets its gradient only through the pixels its anchor's Gaussians cover. Once an
//! object has moved off its anchors' footprint (faster than a knot can follow, or while it passes
//! in front of another object), the photometric loss no longer pulls those anchors towards it and
//! the optimiser fades them out instead: the object vanishes for the rest of the clip
//! (docs/results.md, "Moving objects", Follow-ups 8 and 9). Local gradients cannot find it
//! again; a search can, because the training images themselves say where the object is.
//!
//! How (multi-view photo-consistency, as plane-sweep stereo does): an anchor's *reference colour*
//! is the per-channel median of its reference frame's training images at its position there
//! (frame 0 for the anchors seeded from frame 0's points and for grown ones; the frame it was
//! seeded at for an anchor `train/appearance_seeding.rs` placed on a later object; an anchor whose
//! cameras disagree there is skipped). Only anchors on something that moves at their reference
//! frame (the evaluation's motion mask, in most cameras) whose cameras agree on that colour are
//! considered. When knot j opens, such an anchor whose predicted position at knot j's frame no
//! longer shows its reference colour (the object left it) is searched for: candidate positions on
//! a grid around the prediction are scored by the L1 distance between the sampled colour and the
//! reference, averaged over the best three quarters of the cameras (forgiving the few in which
//! the point is occluded), among the candidates on moving pixels of that frame, and the anchor
//! moves to the best one when it agrees within the tolerance and clearly beats the prediction.
//! Static anchors are never searched. Under `train.knot_search = "patches"` the lost anchors of
//! each cube of `train.knot_search_patch` are searched for together ([`SearchGrouping`]): one
//! colour of a pattern (a checker, stripes) shows at many places, the nearest often a period
//! away, while a patch of the pattern, bounded by the object's outline, fits in one. Costs no
//! rendering: a few bilinear look-ups per camera per candidate, only for the lost anchors.
//!
//! Under `train.knot_consensus = "cells"` ([`place_by_consensus`]) the anchors the search could
//! not place (no colour of their own, or none found), and those it placed by a colour that may
//! alias, move with their neighbours, by the one motion their cameras confirm together, so an
//! object's anchors arrive together.

use crate::data::frames::Frame;
use crate::eval::motion_mask::median;
use crate::raster::RasterCamera;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// The search's parameters (`train.knot_search_radius`, `train.knot_search_tolerance`,
/// `train.knot_search`'s grouping).
#[derive(Clone, Copy, Debug)]
pub struct SearchParams {
    /// Half-width of the cubic search region around the predicted position, world units.
    pub radius: f32,
    /// Largest colour distance ([`score`]: mean-channel L1, colours in [0, 1]) at which the
    /// cameras count as agreeing with the reference.
    pub tolerance: f32,
    pub grouping: SearchGrouping,
}

/// Whether each lost anchor is searched for alone or with the lost anchors near it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SearchGrouping {
    /// Each anchor by its own colour: on a patterned object (a checker, stripes) the point
    /// nearest the prediction with that colour wins, often on another square or stripe, and the
    /// object's anchors scatter.
    PerAnchor,
    /// The lost anchors of each cube of side `side` (world units, at their predicted positions)
    /// share one displacement, the one under which their colours agree best together (a patch of
    /// a pattern has one place where it fits, a single colour many); each anchor then refines it
    /// alone within one coarse grid step where its own colour disagrees there.
    Patches { side: f32 },
}

/// Candidates per axis of the coarse grid (2·COARSE + 1 = 17, spacing radius / COARSE), then of
/// a fine grid (2·FINE + 1 = 9, spacing a quarter of the coarse one) around the best coarse
/// candidate.
const COARSE: i32 = 8;
const FINE: i32 = 4;

/// A point must project into at least this many cameras (and into half of them) to be scored.
const MIN_CAMERAS: usize = 3;

/// The training images of one frame and their cameras (same order).
pub struct FrameViews<'a> {
    pub cameras: &'a [RasterCamera],
    pub images: &'a [&'a Frame],
    /// Per camera, the frame's moving pixels ([H·W], `eval::motion_mask`'s definition: the
    /// ground truth departs from the camera's temporal median).
    pub moving: &'a [Vec<bool>],
}

/// What a search did, for the log.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SearchReport {
    /// Anchors on a moving object at their reference frame whose cameras agree on a colour.
    pub reliable: usize,
    /// Reliable anchors whose predicted position disagrees with it at the knot's frame.
    pub inconsistent: usize,
    /// Anchors moved to a found position.
    pub moved: usize,
}

/// The displacement (world units) that moves each anchor from `predicted[a]` (its position at
/// the knot's frame under the current knots) to where the `target` images show its reference
/// colour, or `None` where it stays. `reference_positions[a]` is the anchor's position at its
/// reference frame, seen by `reference` (the caller groups anchors by reference frame); anchors with `movable[a]` false (their knot cannot move them) are
/// skipped.
pub fn search_displacements(
    reference: &FrameViews,
    reference_positions: &[[f32; 3]],
    target: &FrameViews,
    predicted: &[[f32; 3]],
    movable: &[bool],
    params: SearchParams,
) -> (Vec<Option<[f32; 3]>>, SearchReport) {
    let (placements, report) = search_placements(
        reference,
        reference_positions,
        target,
        predicted,
        movable,
        params,
    );
    let displacements = placements
        .iter()
        .map(|p| match p {
            Placement::Moved(d) => Some(*d),
            _ => None,
        })
        .collect();
    (displacements, report)
}

/// What the search found for each anchor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Placement {
    /// Not searched: its knot cannot move it, too few cameras see it at its reference frame, or
    /// it is not on something moving there.
    Untracked,
    /// On something moving at its reference frame, but its cameras disagree on its colour there
    /// (a point inside or behind the object, or at its outline): it has no colour to search by.
    Unreliable,
    /// Its predicted position shows its reference colour.
    Consistent,
    /// Lost and found: it moves by this displacement from its prediction.
    Moved([f32; 3]),
    /// Lost and not found.
    NotFound,
}

/// [`search_displacements`], with what the search decided for every anchor.
pub fn search_placements(
    reference: &FrameViews,
    reference_positions: &[[f32; 3]],
    target: &FrameViews,
    predicted: &[[f32; 3]],
    movable: &[bool],
    params: SearchParams,
) -> (Vec<Placement>, SearchReport) {
    assert_eq!(reference_positions.len(), predicted.len());
    assert_eq!(movable.len(), predicted.len());
    let tol = params.tolerance;
    let status: Vec<Status> = reference_positions
        .par_iter()
        .zip(predicted.par_iter())
        .zip(movable.par_iter())
        .map(|((&p0, &p), &movable)| {
            if !movable {
                return Status::Skipped;
            }
            let Some(seen) = reference_colour(reference, p0) else {
                return Status::Skipped;
            };
            // Only anchors on something that moves are searched: a static anchor whose colour
            // changes (a moving shadow falls on it) would otherwise be pulled to where its old
            // colour still shows. (A floor anchor that lies *in* a moving shadow at its
            // reference frame passes this test and can follow the shadow: a known gap, docs/results.md
            // Follow-up 10.)
            if !seen.on_moving {
                return Status::Skipped;
            }
            if seen.spread > tol {
                return Status::Unreliable;
            }
            let colour = seen.colour;
            let at_prediction = score(target, p, colour).unwrap_or(f32::INFINITY);
            if at_prediction <= tol {
                return Status::Consistent;
            }
            Status::Lost(Lost {
                predicted: p,
                colour,
                at_prediction,
            })
        })
        .collect();
    // (anchor, what the search needs of it) for every lost anchor.
    let lost: Vec<(usize, Lost)> = status
        .iter()
        .enumerate()
        .filter_map(|(a, s)| match s {
            Status::Lost(l) => Some((a, *l)),
            _ => None,
        })
        .collect();
    // Groups as indices into `lost`.
    let groups: Vec<Vec<usize>> = match params.grouping {
        SearchGrouping::PerAnchor => (0..lost.len()).map(|i| vec![i]).collect(),
        SearchGrouping::Patches { side } => {
            let mut cells: BTreeMap<[i64; 3], Vec<usize>> = BTreeMap::new();
            for (i, (_, l)) in lost.iter().enumerate() {
                let key = l.predicted.map(|v| (v / side).floor() as i64);
                cells.entry(key).or_default().push(i);
            }
            cells.into_values().collect()
        }
    };
    let moves: Vec<(usize, [f32; 3])> = groups
        .par_iter()
        .flat_map_iter(|group| {
            let members: Vec<Lost> = group.iter().map(|&i| lost[i].1).collect();
            let found = search_group(target, &members, params);
            group
                .iter()
                .zip(found)
                .filter_map(|(&i, d)| d.map(|d| (lost[i].0, d)))
                .collect::<Vec<_>>()
        })
        .collect();
    let mut placements: Vec<Placement> = status
        .iter()
        .map(|s| match s {
            Status::Skipped => Placement::Untracked,
            Status::Unreliable => Placement::Unreliable,
            Status::Consistent => Placement::Consistent,
            Status::Lost(_) => Placement::NotFound,
        })
        .collect();
    for &(a, d) in &moves {
        placements[a] = Placement::Moved(d);
    }
    let report = SearchReport {
        reliable: status
            .iter()
            .filter(|s| matches!(s, Status::Consistent | Status::Lost(_)))
            .count(),
        inconsistent: lost.len(),
        moved: moves.len(),
    };
    (placements, report)
}

/// Where an anchor stands before the search.
enum Status {
    /// Not searched: its knot cannot move it, too few cameras see it, or it is not on something
    /// moving.
    Skipped,
    /// On something moving, but its cameras disagree on its reference colour.
    Unreliable,
    /// Its predicted position shows its reference colour.
    Consistent,
    Lost(Lost),
}

/// A lost anchor: its predicted position no longer shows its reference colour.
#[derive(Clone, Copy)]
struct Lost {
    predicted: [f32; 3],
    colour: [f32; 3],
    /// Its [`score`] at the prediction (infinite where too few cameras see it).
    at_prediction: f32,
}

/// The displacement of each member of a group of lost anchors searched together (a group of one
/// under [`SearchGrouping::PerAnchor`]). An anchor moves only to a consistent place that is
/// clearly better than its prediction (by one tolerance), so colour noise never moves one.
fn search_group(target: &FrameViews, lost: &[Lost], params: SearchParams) -> Vec<Option<[f32; 3]>> {
    let tol = params.tolerance;
    let acceptable = |l: &Lost, s: f32| s <= tol && s + tol < l.at_prediction;
    let Some((trimmed, shared)) = grid_search(target, lost, params) else {
        return vec![None; lost.len()];
    };
    if let [l] = lost {
        // A group of one: the scan's score is the anchor's own.
        return vec![acceptable(l, trimmed).then_some(shared)];
    }
    let (_, fine) = spacings(params);
    lost.iter()
        .map(|l| {
            // The patch's displacement where the anchor's own colour agrees there; else the
            // anchor's best place within one coarse step of it (an anchor near a patch's
            // border, or on a part that turned).
            let own = score(target, add(l.predicted, shared), l.colour);
            if own.is_some_and(|s| acceptable(l, s)) {
                return Some(shared);
            }
            let (_, s, d) = scan(target, std::slice::from_ref(l), shared, fine, FINE, params)?;
            acceptable(l, s).then_some(d)
        })
        .collect()
}

/// The coarse and the fine grid's spacing.
fn spacings(params: SearchParams) -> (f32, f32) {
    let coarse = params.radius / COARSE as f32;
    (coarse, coarse / FINE as f32)
}

fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// The (2·half + 1)³ points `spacing` apart around `around`, x outermost.
fn grid(around: [f32; 3], spacing: f32, half: i32) -> impl Iterator<Item = [f32; 3]> {
    (-half..=half).flat_map(move |i| {
        (-half..=half).flat_map(move |j| {
            (-half..=half).map(move |k| {
                [
                    around[0] + i as f32 * spacing,
                    around[1] + j as f32 * spacing,
                    around[2] + k as f32 * spacing,
                ]
            })
        })
    })
}

/// The best displacement for the group (scored by [`scan`]) on a coarse grid within the radius,
/// refined on a finer grid around the coarse winner, with its trimmed score.
fn grid_search(
    target: &FrameViews,
    lost: &[Lost],
    params: SearchParams,
) -> Option<(f32, [f32; 3])> {
    let (coarse, fine) = spacings(params);
    let (_, _, d) = scan(target, lost, [0.0; 3], coarse, COARSE, params)?;
    let (_, trimmed, d) = scan(target, lost, d, fine, FINE, params)?;
    Some((trimmed, d))
}

/// The best displacement (rank, trimmed score, displacement) on the grid of (2·half + 1)³
/// displacements `spacing` apart around `around`, for a group of lost anchors moved together.
/// A displacement is scored where at least half of the group is seen and most of what is seen
/// lies on moving pixels (a lost object is where something moves: a dark anchor would match
/// every static shadow). Candidates are ranked by the group's mean over *all* the cameras that
/// see them: the trimmed score forgives a quarter of the views, so it ties between points inside
/// an object and points beside it that three quarters of the ring see against it (unit test
/// below); the mean prefers the inside. Remaining ties go to the smallest displacement (a
/// hundredth of the tolerance per radius).
fn scan(
    target: &FrameViews,
    lost: &[Lost],
    around: [f32; 3],
    spacing: f32,
    half: i32,
    params: SearchParams,
) -> Option<(f32, f32, [f32; 3])> {
    let tie = 0.01 * params.tolerance / params.radius.max(f32::MIN_POSITIVE);
    let mut best: Option<(f32, f32, [f32; 3])> = None;
    for d in grid(around, spacing, half) {
        let (mut seen, mut moving, mut mean, mut trimmed) = (0usize, 0usize, 0.0f32, 0.0f32);
        for l in lost {
            let Some(agreement) = agreement(target, add(l.predicted, d), l.colour) else {
                continue;
            };
            seen += 1;
            moving += usize::from(agreement.on_moving);
            mean += agreement.mean;
            trimmed += agreement.trimmed;
        }
        if seen == 0 || 2 * seen < lost.len() || 2 * moving <= seen {
            continue;
        }
        let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let rank = mean / seen as f32 + tie * length;
        if best.is_none_or(|(b, _, _)| rank < b) {
            best = Some((rank, trimmed / seen as f32, d));
        }
    }
    best
}

/// How well the cameras that see a point agree with a colour: the L1 distance (mean over the
/// channels) between what each image shows there and the colour, averaged over the best three
/// quarters of the cameras (`trimmed`, forgiving the few in which the point is occluded: a
/// median, half the views, let points beside an object score as well as points in it) and over
/// all of them (`mean`).
pub(crate) struct Agreement {
    pub(crate) trimmed: f32,
    pub(crate) mean: f32,
    /// Whether most of those cameras see a moving pixel there.
    pub(crate) on_moving: bool,
}

/// [`Agreement::trimmed`] at `p`.
fn score(views: &FrameViews, p: [f32; 3], colour: [f32; 3]) -> Option<f32> {
    agreement(views, p, colour).map(|a| a.trimmed)
}

/// `None` where too few cameras see `p`.
pub(crate) fn agreement(views: &FrameViews, p: [f32; 3], colour: [f32; 3]) -> Option<Agreement> {
    // On the stack for rigs up to 64 cameras (5,642 candidates per lost anchor).
    let mut stack = [0.0f32; 64];
    let mut heap = Vec::new();
    let (mut n, mut moving) = (0, 0);
    for ((camera, image), mask) in views.cameras.iter().zip(views.images).zip(views.moving) {
        let Some(xy) = project(camera, p) else {
            continue;
        };
        let Some(c) = bilinear(image, xy) else {
            continue;
        };
        moving += usize::from(mask_at(mask, image, xy));
        let d = (0..3).map(|i| (c[i] - colour[i]).abs()).sum::<f32>() / 3.0;
        if n < stack.len() {
            stack[n] = d;
        } else {
            heap.push(d);
        }
        n += 1;
    }
    if !enough(n, views.cameras.len()) {
        return None;
    }
    let values = if heap.is_empty() {
        &mut stack[..n]
    } else {
        heap.extend_from_slice(&stack);
        &mut heap[..]
    };
    let mean = values.iter().sum::<f32>() / n as f32;
    Some(Agreement {
        trimmed: trimmed_mean(values),
        mean,
        on_moving: 2 * moving > n,
    })
}

/// The mask's value at the pixel containing `xy` (inside the image).
fn mask_at(mask: &[bool], image: &Frame, xy: [f32; 2]) -> bool {
    let (w, h) = (image.width as usize, image.height as usize);
    let (x, y) = ((xy[0] as usize).min(w - 1), (xy[1] as usize).min(h - 1));
    mask[y * w + x]
}

/// The mean of the smallest ⌈3n/4⌉ values.
fn trimmed_mean(values: &mut [f32]) -> f32 {
    values.sort_unstable_by(f32::total_cmp);
    let keep = (3 * values.len()).div_ceil(4);
    values[..keep].iter().sum::<f32>() / keep as f32
}

/// What the reference frame's cameras show at an anchor.
struct Seen {
    /// Per-channel median colour.
    colour: [f32; 3],
    /// L1 deviation from `colour`, averaged as [`Agreement::trimmed`].
    spread: f32,
    /// Whether most cameras that see the point see a moving pixel there.
    on_moving: bool,
}

fn reference_colour(views: &FrameViews, p: [f32; 3]) -> Option<Seen> {
    let mut colours = Vec::with_capacity(views.cameras.len());
    let mut moving = 0;
    for ((camera, image), mask) in views.cameras.iter().zip(views.images).zip(views.moving) {
        let Some(xy) = project(camera, p) else {
            continue;
        };
        let Some(c) = bilinear(image, xy) else {
            continue;
        };
        colours.push(c);
        moving += usize::from(mask_at(mask, image, xy));
    }
    if !enough(colours.len(), views.cameras.len()) {
        return None;
    }
    let on_moving = 2 * moving > colours.len();
    let colour: [f32; 3] = std::array::from_fn(|i| {
        let mut channel: Vec<f32> = colours.iter().map(|c| c[i]).collect();
        median(&mut channel)
    });
    let mut deviations: Vec<f32> = colours
        .iter()
        .map(|c| (0..3).map(|i| (c[i] - colour[i]).abs()).sum::<f32>() / 3.0)
        .collect();
    Some(Seen {
        colour,
        spread: trimmed_mean(&mut deviations),
        on_moving,
    })
}

/// What the cameras of `views` show at `p` (`None` where too few see it): whether most of them
/// see a moving pixel there, and how far they disagree on its colour (mean-channel L1 from
/// their median colour, averaged over the best three quarters: small on a surface they see,
/// large for a point hidden behind one, where each camera sees another point of it).
pub(crate) fn seen_at(views: &FrameViews, p: [f32; 3]) -> Option<(bool, f32)> {
    reference_colour(views, p).map(|seen| (seen.on_moving, seen.spread))
}

/// Most anchors of a cell that [`place_by_consensus`] scores a motion by (spread evenly over
/// the cell's members): enough to pin a cell's motion, few enough that a knot's placement costs
/// about a second.
const MAX_SCORED: usize = 32;

/// Coarse motions [`place_by_consensus`] refines per cell.
const REFINED_COARSE: usize = 4;

/// What [`place_by_consensus`] changed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ConsensusReport {
    /// Anchors the search did not place (no colour of their own, or lost and not found) moved
    /// with their cell.
    pub adopted: usize,
    /// Anchors the search placed that take a neighbourhood's motion their own cameras confirm
    /// instead (a single colour's match may be a stripe or a square of a pattern off).
    pub corrected: usize,
}

/// `train.knot_consensus = "cells"` (not in GIFStream or ACA-GS): places an object's anchors
/// together, by the motion their cameras confirm together, where the search alone would leave
/// them behind.
///
/// Why: anchor by anchor, the search places only anchors whose cameras agree on one colour (the
/// visible surface of an object, away from its outline) and finds them only where that colour is
/// unique near the prediction; the rest of the object — points inside or behind it, at its
/// outline, on a stripe that repeats — stay at the held knot, off the object, get no gradient
/// towards it and are faded out (docs/results.md, Follow-up 16: two thirds of the `fast`
/// sphere's anchors; placed right, the gradient keeps them). A median of the found anchors'
/// motions does not fix it: aliased matches are the majority in places.
///
/// How: the evidence is *camera by camera* — each camera's pixel at an anchor's reference
/// position in the reference frame against the same camera's pixel where a motion puts it in the
/// knot's frame ([`SameViewProbe`]). That needs no colour the cameras agree on, so it
/// scores points inside or behind an object too, and a patch of anchors, each with its cameras'
/// views, fits its object's motion in one place only. The anchors the search considered (on
/// something moving at their reference frame) are grouped in cubes of side `cell` at their
/// reference positions; each cube with an anchor the search could not confirm gets one motion
/// (from the reference frame to the knot's), found on the search's grids (`params.radius`)
/// around its members' median motion as they stand (predicted, or where the search put them), scored by the mean agreement over up to
/// [`MAX_SCORED`] anchors of it and its neighbour cells, among motions that put most of them on
/// moving pixels of the knot's frame. Each anchor the search did not confirm then takes, of
/// its own cell's and the 26 neighbour cells' motions, the one its own cameras confirm best
/// (a cell straddling two objects, or one whose motion aliased, does not decide alone), where
/// that puts it on moving pixels with agreement within `params.tolerance`: an anchor the search
/// found, always (a shared motion its cameras confirm beats a single colour's match, which may
/// alias); any other, only where its cameras agree better than at its prediction. Anchors whose
/// prediction shows their colour are left alone. A motion from the reference frame, not a
/// correction of the prediction, so an anchor that lagged at earlier knots is brought back
/// too. Returns each anchor's displacement from `predicted` (the search's own where kept),
/// `None` where it stays.
pub fn place_by_consensus(
    reference: &FrameViews,
    reference_positions: &[[f32; 3]],
    target: &FrameViews,
    predicted: &[[f32; 3]],
    placements: &[Placement],
    cell: f32,
    params: SearchParams,
) -> (Vec<Option<[f32; 3]>>, ConsensusReport) {
    let n = placements.len();
    assert_eq!(reference_positions.len(), n);
    assert_eq!(predicted.len(), n);
    let sub = |a: [f32; 3], b: [f32; 3]| -> [f32; 3] { std::array::from_fn(|i| a[i] - b[i]) };
    // Where each anchor stands now: the search's place, or its prediction.
    let standing: Vec<[f32; 3]> = (0..n)
        .map(|a| match placements[a] {
            Placement::Moved(d) => add(predicted[a], d),
            _ => predicted[a],
        })
        .collect();
    let mut cells: BTreeMap<[i64; 3], Vec<usize>> = BTreeMap::new();
    for (a, placement) in placements.iter().enumerate() {
        if *placement != Placement::Untracked {
            let key = reference_positions[a].map(|v| (v / cell).floor() as i64);
            cells.entry(key).or_default().push(a);
        }
    }
    let probes = SameViewProbe::new(reference, reference_positions, target, |a| {
        placements[a] != Placement::Untracked
    });
    let (coarse, fine) = spacings(params);
    let tie = 0.01 * params.tolerance / params.radius.max(f32::MIN_POSITIVE);
    let keys: Vec<[i64; 3]> = cells.keys().copied().collect();
    // Each cell's motion, scored over its members and its neighbour cells' (the support), so a
    // cell at an object's outline with a few members is pinned by its neighbours too.
    let motions: BTreeMap<[i64; 3], [f32; 3]> = keys
        .par_iter()
        .filter(|key| {
            cells[*key]
                .iter()
                .any(|&a| placements[a] != Placement::Consistent)
        })
        .filter_map(|key| {
            let members = &cells[key];
            let support: Vec<usize> = neighbour_cells(*key)
                .filter_map(|k| cells.get(&k))
                .flatten()
                .copied()
                .collect();
            let stride = support.len().div_ceil(MAX_SCORED);
            let scored: Vec<usize> = support.iter().copied().step_by(stride).collect();
            // Around where the members stand now (the search's places count: where most were
            // found, the object went about there).
            let centre = median_shift(members, reference_positions, &standing);
            // The best motion on a grid of (2·half + 1)³ motions `spacing` apart around
            // `around`: least mean agreement over the scored anchors that see it (at least
            // half of them); ties to the motion nearest the centre.
            // The grid of (2·half + 1)³ motions `spacing` apart around `around`, ranked (best
            // first) by the mean agreement over the scored anchors that see them (at least half
            // of them); ties to the motion nearest the centre.
            let scan = |around: [f32; 3], spacing: f32, half: i32| -> Vec<(f32, [f32; 3])> {
                let mut ranked = Vec::new();
                for m in grid(around, spacing, half) {
                    let (mut seen, mut moving, mut total) = (0usize, 0usize, 0.0f32);
                    for &a in &scored {
                        let probe = probes.at(a, add(reference_positions[a], m));
                        if let Some(s) = probe.agreement {
                            seen += 1;
                            moving += usize::from(probe.moving);
                            total += s;
                        }
                    }
                    // As the search's scan: an object is where something moves.
                    if seen == 0 || 2 * seen < scored.len() || 2 * moving <= seen {
                        continue;
                    }
                    let off = sub(m, centre);
                    let length = (off[0] * off[0] + off[1] * off[1] + off[2] * off[2]).sqrt();
                    ranked.push((total / seen as f32 + tie * length, m));
                }
                ranked.sort_by(|x, y| x.0.total_cmp(&y.0));
                ranked
            };
            // A textured object's true motion can fall between coarse grid points while an
            // aliased one sits on one: the best few coarse motions are each refined, and the
            // best refined one wins.
            let (_, motion) = scan(centre, coarse, COARSE)
                .into_iter()
                .take(REFINED_COARSE)
                .filter_map(|(_, m)| scan(m, fine, FINE).into_iter().next())
                .min_by(|x, y| x.0.total_cmp(&y.0))?;
            Some((*key, motion))
        })
        .collect();
    // Each anchor the search did not confirm takes, of its own cell's and the neighbour cells'
    // motions, the one its own cameras confirm best (a cell straddling two objects, or one whose
    // motion aliased, does not decide alone).
    let placed: Vec<(usize, [f32; 3], bool)> = keys
        .par_iter()
        .flat_map_iter(|key| {
            let choices: Vec<[f32; 3]> = neighbour_cells(*key)
                .filter_map(|k| motions.get(&k).copied())
                .collect();
            cells[key]
                .iter()
                .filter(|&&a| placements[a] != Placement::Consistent)
                .filter_map(|&a| {
                    let (there, place) = choices
                        .iter()
                        .map(|&m| add(reference_positions[a], m))
                        .filter_map(|place| {
                            let probe = probes.at(a, place);
                            Some((probe.agreement.filter(|_| probe.moving)?, place))
                        })
                        .min_by(|x, y| x.0.total_cmp(&y.0))?;
                    // A found anchor's own match loses to a motion its cameras confirm that its
                    // neighbours share (its colour alone may alias); any other anchor moves only
                    // where its cameras agree better than where it stands.
                    let found = matches!(placements[a], Placement::Moved(_));
                    let here = probes.at(a, standing[a]).agreement.unwrap_or(f32::INFINITY);
                    let better = found || there < here;
                    (there <= params.tolerance && better && place != standing[a])
                        .then(|| (a, sub(place, predicted[a]), found))
                })
                .collect::<Vec<_>>()
        })
        .collect();
    let mut displacements: Vec<Option<[f32; 3]>> = placements
        .iter()
        .map(|p| match p {
            Placement::Moved(d) => Some(*d),
            _ => None,
        })
        .collect();
    let mut report = ConsensusReport::default();
    for (a, d, corrected) in placed {
        displacements[a] = Some(d);
        if corrected {
            report.corrected += 1;
        } else {
            report.adopted += 1;
        }
    }
    (displacements, report)
}

/// The per-component median of `to[a] − from[a]` over `members` (a group of anchors' typical
/// displacement, robust to the few that went elsewhere).
pub(crate) fn median_shift(members: &[usize], from: &[[f32; 3]], to: &[[f32; 3]]) -> [f32; 3] {
    std::array::from_fn(|i| {
        let mut component: Vec<f32> = members.iter().map(|&a| to[a][i] - from[a][i]).collect();
        median(&mut component)
    })
}

/// A cell and its 26 neighbours, the cell first.
fn neighbour_cells(key: [i64; 3]) -> impl Iterator<Item = [i64; 3]> {
    let offsets = (0..27).map(|i| [i % 3, (i / 3) % 3, i / 9].map(|o| (o + 1) % 3 - 1));
    offsets.map(move |o| [key[0] + o[0], key[1] + o[1], key[2] + o[2]])
}

/// Each camera's view of an anchor at its reference position (looked up once), against the same
/// camera's view of a place in the knot's frame.
pub(crate) struct SameViewProbe<'a> {
    target: &'a FrameViews<'a>,
    cameras: usize,
    /// Per anchor, its row of `before` (`u32::MAX` for anchors not probed).
    row: Vec<u32>,
    /// [probed anchor × camera]: the reference frame's colour there.
    before: Vec<Option<[f32; 3]>>,
}

/// What [`SameViewProbe::at`] sees.
pub(crate) struct Probed {
    /// Mean-channel L1 distance between each camera's view of the anchor at the reference frame
    /// and its view of the place in the knot's frame, averaged over the best three quarters of
    /// the cameras that see both; `None` where too few cameras see both.
    pub(crate) agreement: Option<f32>,
    /// Whether most of the cameras that see the place see a moving pixel there.
    pub(crate) moving: bool,
}

impl<'a> SameViewProbe<'a> {
    pub(crate) fn new(
        reference: &FrameViews,
        positions: &[[f32; 3]],
        target: &'a FrameViews<'a>,
        probed: impl Fn(usize) -> bool,
    ) -> Self {
        assert_eq!(
            reference.cameras.len(),
            target.cameras.len(),
            "the same rig at both frames"
        );
        let cameras = reference.cameras.len();
        let probed: Vec<usize> = (0..positions.len()).filter(|&a| probed(a)).collect();
        let mut row = vec![u32::MAX; positions.len()];
        for (r, &a) in probed.iter().enumerate() {
            row[a] = u32::try_from(r).expect("fewer than 2³² anchors");
        }
        let before = probed
            .par_iter()
            .flat_map_iter(|&a| {
                (0..cameras).map(move |i| {
                    let xy = project(&reference.cameras[i], positions[a])?;
                    bilinear(reference.images[i], xy)
                })
            })
            .collect();
        Self {
            target,
            cameras,
            row,
            before,
        }
    }

    pub(crate) fn at(&self, a: usize, at: [f32; 3]) -> Probed {
        // On the stack for rigs up to 64 cameras (it runs for every candidate motion).
        let mut stack = [0.0f32; 64];
        let mut heap = Vec::new();
        let (mut both, mut seen, mut moving) = (0usize, 0usize, 0usize);
        let views = self.target;
        for (i, ((camera, image), mask)) in views
            .cameras
            .iter()
            .zip(views.images)
            .zip(views.moving)
            .enumerate()
        {
            let Some(xy) = project(camera, at) else {
                continue;
            };
            let Some(after) = bilinear(image, xy) else {
                continue;
            };
            seen += 1;
            moving += usize::from(mask_at(mask, image, xy));
            let Some(before) = self.before[self.row[a] as usize * self.cameras + i] else {
                continue;
            };
            let d = (0..3).map(|c| (before[c] - after[c]).abs()).sum::<f32>() / 3.0;
            if both < stack.len() {
                stack[both] = d;
            } else {
                heap.push(d);
            }
            both += 1;
        }
        let agreement = enough(both, self.cameras).then(|| {
            if heap.is_empty() {
                trimmed_mean(&mut stack[..both])
            } else {
                heap.extend_from_slice(&stack);
                trimmed_mean(&mut heap)
            }
        });
        Probed {
            agreement,
            moving: 2 * moving > seen,
        }
    }
}

fn enough(seen: usize, cameras: usize) -> bool {
    seen >= MIN_CAMERAS && 2 * seen >= cameras
}

/// Pixel coordinates (pixel centres at +0.5) of `p`, `None` behind the camera.
pub(crate) fn project(camera: &RasterCamera, p: [f32; 3]) -> Option<[f32; 2]> {
    project_with_depth(camera, p).map(|(xy, _)| xy)
}

/// [`project`] and the point's camera depth (z).
pub(crate) fn project_with_depth(camera: &RasterCamera, p: [f32; 3]) -> Option<([f32; 2], f32)> {
    let m = &camera.world_to_camera;
    let c: [f32; 3] =
        std::array::from_fn(|i| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3]);
    (c[2] > 1e-4).then(|| {
        (
            [
                camera.fx * c[0] / c[2] + camera.cx,
                camera.fy * c[1] / c[2] + camera.cy,
            ],
            c[2],
        )
    })
}

/// The image's colour at pixel position `xy` (bilinear between pixel centres), `None` outside
/// the image.
pub(crate) fn bilinear(image: &Frame, xy: [f32; 2]) -> Option<[f32; 3]> {
    let (w, h) = (image.width as usize, image.height as usize);
    let (x, y) = (xy[0] - 0.5, xy[1] - 0.5);
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |xi: usize, yi: usize, c: usize| image.rgb[(yi * w + xi) * 3 + c];
    Some(std::array::from_fn(|c| {
        (at(x0, y0, c) * (1.0 - fx) + at(x1, y0, c) * fx) * (1.0 - fy)
            + (at(x0, y1, c) * (1.0 - fx) + at(x1, y1, c) * fx) * fy
    }))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    const SIZE: u32 = 64;
    const FOCAL: f32 = 60.0;
    pub(crate) const BALL_RADIUS: f32 = 0.35;
    const BALL_COLOUR: [f32; 3] = [0.1, 0.8, 0.2];
    const BAND_COLOUR: [f32; 3] = [0.8, 0.1, 0.7];

    /// Eight cameras on a ring of radius 4 at height 1.5, looking at (0, 0.3, 0) (x right,
    /// y down, z forward in camera space).
    pub(crate) fn rig() -> Vec<RasterCamera> {
        (0..8)
            .map(|i| {
                let angle = i as f32 * std::f32::consts::TAU / 8.0;
                let eye = [4.0 * angle.cos(), 1.5, 4.0 * angle.sin()];
                let forward = normalize(sub([0.0, 0.3, 0.0], eye));
                let right = normalize(cross(forward, [0.0, 1.0, 0.0]));
                let down = cross(forward, right);
                let rows = [right, down, forward];
                let t: [f32; 3] = std::array::from_fn(|r| -dot(rows[r], eye));
                RasterCamera {
                    width: SIZE,
                    height: SIZE,
                    fx: FOCAL,
                    fy: FOCAL,
                    cx: SIZE as f32 / 2.0,
                    cy: SIZE as f32 / 2.0,
                    world_to_camera: [
                        [rows[0][0], rows[0][1], rows[0][2], t[0]],
                        [rows[1][0], rows[1][1], rows[1][2], t[1]],
                        [rows[2][0], rows[2][1], rows[2][2], t[2]],
                        [0.0, 0.0, 0.0, 1.0],
                    ],
                }
            })
            .collect()
    }

    /// Ray-traced image: a green ball at `ball` above a grey checkerboard floor (y = 0, cells
    /// 0.25 wide) under a pale sky; returns the image and the ball's pixels.
    pub(crate) fn render(camera: &RasterCamera, ball: [f32; 3]) -> (Frame, Vec<bool>) {
        render_ball(camera, ball, None)
    }

    /// [`render`] with the ball painted in horizontal bands (green and magenta, each `band`
    /// high, from the ball's centre up), when `band` is given.
    fn render_ball(camera: &RasterCamera, ball: [f32; 3], band: Option<f32>) -> (Frame, Vec<bool>) {
        let m = &camera.world_to_camera;
        let rows: [[f32; 3]; 3] = std::array::from_fn(|r| [m[r][0], m[r][1], m[r][2]]);
        let t = [m[0][3], m[1][3], m[2][3]];
        // Camera centre: −Rᵀt.
        let eye: [f32; 3] =
            std::array::from_fn(|i| -(0..3).map(|r| rows[r][i] * t[r]).sum::<f32>());
        let mut rgb = Vec::new();
        let mut on_ball = Vec::new();
        for y in 0..SIZE {
            for x in 0..SIZE {
                let d_cam = [
                    (x as f32 + 0.5 - camera.cx) / camera.fx,
                    (y as f32 + 0.5 - camera.cy) / camera.fy,
                    1.0,
                ];
                let d = normalize(std::array::from_fn(|i| {
                    (0..3).map(|r| rows[r][i] * d_cam[r]).sum()
                }));
                let oc = sub(eye, ball);
                let (b, c) = (dot(oc, d), dot(oc, oc) - BALL_RADIUS * BALL_RADIUS);
                // Distance to the ball's near surface, where the ray meets it in front.
                let hit = (b * b - c > 0.0)
                    .then(|| -b - (b * b - c).sqrt())
                    .filter(|&s| s > 0.0);
                let hit_ball = hit.is_some();
                let colour = if let Some(s) = hit {
                    let height = eye[1] + s * d[1] - ball[1];
                    match band {
                        Some(band) if (height / band).floor().rem_euclid(2.0) >= 1.0 => BAND_COLOUR,
                        _ => BALL_COLOUR,
                    }
                } else if d[1] < -1e-3 {
                    let s = -eye[1] / d[1];
                    let (px, pz) = (eye[0] + s * d[0], eye[2] + s * d[2]);
                    let cell =
                        ((px / 0.25).floor() as i32 + (pz / 0.25).floor() as i32).rem_euclid(2);
                    if cell == 0 {
                        [0.3, 0.3, 0.35]
                    } else {
                        [0.65, 0.6, 0.6]
                    }
                } else {
                    [0.85, 0.9, 0.95]
                };
                rgb.extend_from_slice(&colour);
                on_ball.push(hit_ball);
            }
        }
        (
            Frame {
                width: SIZE,
                height: SIZE,
                rgb,
            },
            on_ball,
        )
    }

    fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|i| a[i] - b[i])
    }
    fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
        (0..3).map(|i| a[i] * b[i]).sum()
    }
    fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    }
    fn normalize(a: [f32; 3]) -> [f32; 3] {
        let n = dot(a, a).sqrt();
        a.map(|v| v / n)
    }
    fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
        dot(sub(a, b), sub(a, b)).sqrt()
    }

    const BALL_AT_0: [f32; 3] = [-0.6, 0.5, 0.0];
    pub(crate) const BALL_AT_F: [f32; 3] = [0.2, 0.6, 0.3];
    const PARAMS: SearchParams = SearchParams {
        radius: 1.0,
        tolerance: 0.08,
        grouping: SearchGrouping::PerAnchor,
    };

    /// Anchors: two inside the ball at frame 0 (held there by their knots), one on the floor.
    fn anchors() -> Vec<[f32; 3]> {
        vec![BALL_AT_0, [-0.5, 0.45, 0.1], [0.9, 0.0, -0.7]]
    }

    /// Searches with the ball moved from BALL_AT_0 to BALL_AT_F, every anchor predicted where
    /// it was at frame 0 (held knots); `moving` overrides the moving-pixel masks (else the
    /// ball's pixels in either frame); `movable` applies to every anchor.
    fn search(
        params: SearchParams,
        moving: Option<bool>,
        movable: bool,
    ) -> (Vec<Option<[f32; 3]>>, SearchReport) {
        let cameras = rig();
        let (reference, on_ball_0): (Vec<Frame>, Vec<Vec<bool>>) =
            cameras.iter().map(|c| render(c, BALL_AT_0)).unzip();
        let (target, on_ball_f): (Vec<Frame>, Vec<Vec<bool>>) =
            cameras.iter().map(|c| render(c, BALL_AT_F)).unzip();
        // What the motion mask marks in either frame: the ball's pixels in both.
        let either: Vec<Vec<bool>> = on_ball_0
            .iter()
            .zip(&on_ball_f)
            .map(|(a, b)| a.iter().zip(b).map(|(&a, &b)| a || b).collect())
            .collect();
        let masks: Vec<Vec<bool>> = match moving {
            Some(all) => either.iter().map(|m| vec![all; m.len()]).collect(),
            None => either,
        };
        let reference_refs: Vec<&Frame> = reference.iter().collect();
        let target_refs: Vec<&Frame> = target.iter().collect();
        search_displacements(
            &FrameViews {
                cameras: &cameras,
                images: &reference_refs,
                moving: &masks,
            },
            &anchors(),
            &FrameViews {
                cameras: &cameras,
                images: &target_refs,
                moving: &masks,
            },
            &anchors(),
            &[movable; 3],
            params,
        )
    }

    #[test]
    fn a_lost_anchor_is_moved_into_its_object_and_a_static_one_stays() {
        let (moves, report) = search(PARAMS, None, true);
        assert_eq!(
            report,
            SearchReport {
                reliable: 2,
                inconsistent: 2,
                moved: 2
            }
        );
        for (a, anchor) in anchors().iter().enumerate().take(2) {
            let delta = moves[a].expect("the ball's anchors are found");
            let found = [
                anchor[0] + delta[0],
                anchor[1] + delta[1],
                anchor[2] + delta[2],
            ];
            // Inside the ball at frame f (the search grid's fine step is 1/32).
            assert!(
                distance(found, BALL_AT_F) < BALL_RADIUS,
                "anchor {a} moved to {found:?}, {} from the ball's centre",
                distance(found, BALL_AT_F)
            );
        }
        assert_eq!(moves[2], None, "the floor anchor is not on a moving object");
    }

    #[test]
    fn an_object_beyond_the_radius_is_not_found_and_nothing_moves_without_evidence() {
        // Negative control: the ball moved 0.86; the search reaches 1.125 radii per axis (the
        // fine grid around a border winner), 0.17 at radius 0.15, leaving no candidate within
        // 0.6 of the ball's centre. (At radius 0.3 one anchor does move, to a point 0.375 from the
        // centre, at the ball's edge (0.35 plus a third of a pixel's footprint), as far as that
        // search reaches: an edge point agrees in enough views; the photometric loss takes over
        // from there.)
        let (moves, report) = search(
            SearchParams {
                radius: 0.15,
                ..PARAMS
            },
            None,
            true,
        );
        assert_eq!((report.inconsistent, report.moved), (2, 0));
        assert!(moves.iter().all(Option::is_none));
        // Every pixel marked moving: the floor anchor is searched for only if its colour left
        // it, which it did not (the ball never covers it in most cameras).
        let (moves, report) = search(PARAMS, Some(true), true);
        assert_eq!(report.reliable, 3);
        assert_eq!(moves[2], None);
        // No pixel moving: nothing is searched.
        let (moves, report) = search(PARAMS, Some(false), true);
        assert_eq!(report, SearchReport::default());
        assert!(moves.iter().all(Option::is_none));
        // Anchors whose knot cannot move them (motion gate shut) are not searched.
        let (moves, report) = search(PARAMS, None, false);
        assert_eq!(report, SearchReport::default());
        assert!(moves.iter().all(Option::is_none));
    }

    /// A banded ball moved by more than half its pattern's period along the bands' normal: each
    /// anchor alone matches the nearest band of its colour, which is the wrong one for some; the
    /// anchors searched as one patch fit the pattern in one place only (the ball's outline
    /// bounds it), and every one moves by the ball's displacement.
    #[test]
    fn a_patch_of_a_patterned_object_moves_together_where_single_anchors_alias() {
        const BAND: f32 = 0.14;
        let from = [-0.6, 0.5, 0.0];
        let to = [0.0, 0.72, 0.2];
        let truth: [f32; 3] = std::array::from_fn(|i| to[i] - from[i]);
        let cameras = rig();
        let (reference, on_0): (Vec<Frame>, Vec<Vec<bool>>) = cameras
            .iter()
            .map(|c| render_ball(c, from, Some(BAND)))
            .unzip();
        let (target, on_f): (Vec<Frame>, Vec<Vec<bool>>) = cameras
            .iter()
            .map(|c| render_ball(c, to, Some(BAND)))
            .unzip();
        let masks: Vec<Vec<bool>> = on_0
            .iter()
            .zip(&on_f)
            .map(|(a, b)| a.iter().zip(b).map(|(&a, &b)| a || b).collect())
            .collect();
        // Anchors at the middle of each band along the ball's vertical axis and beside it.
        let anchors: Vec<[f32; 3]> = [-1.5f32, -0.5, 0.5, 1.5]
            .iter()
            .flat_map(|&k| {
                [[0.0, 0.0], [0.12, 0.0], [-0.12, 0.0], [0.0, 0.12]]
                    .map(move |[dx, dz]| [from[0] + dx, from[1] + k * BAND, from[2] + dz])
            })
            .collect();
        let reference_refs: Vec<&Frame> = reference.iter().collect();
        let target_refs: Vec<&Frame> = target.iter().collect();
        let run = |grouping| {
            search_displacements(
                &FrameViews {
                    cameras: &cameras,
                    images: &reference_refs,
                    moving: &masks,
                },
                &anchors,
                &FrameViews {
                    cameras: &cameras,
                    images: &target_refs,
                    moving: &masks,
                },
                &anchors,
                &vec![true; anchors.len()],
                SearchParams { grouping, ..PARAMS },
            )
        };
        let band_error = |moves: &[Option<[f32; 3]>]| -> Vec<f32> {
            moves
                .iter()
                .flatten()
                .map(|d| (d[1] - truth[1]).abs())
                .collect()
        };
        let (single, single_report) = run(SearchGrouping::PerAnchor);
        let (patch, patch_report) = run(SearchGrouping::Patches { side: 1.0 });
        // The same anchors are searched and the same number found either way; what differs is
        // where they go.
        assert_eq!(single_report, patch_report);
        assert!(patch_report.moved >= 5, "{patch_report:?}");
        // Alone, some anchors land a band (or more) off: the nearest band of their colour.
        let aliased = band_error(&single).iter().filter(|&&e| e > BAND).count();
        assert!(aliased >= 2, "{:?}", band_error(&single));
        // Together, every found anchor lands on its own band (the ball's displacement along the
        // bands' normal within two steps of the fine grid, 1/32 each); most take the patch's
        // displacement itself, that of the ball within two fine steps per axis (the others
        // refine it alone where their own colour disagrees there).
        assert!(
            band_error(&patch).iter().all(|&e| e < 0.07),
            "{:?}",
            band_error(&patch)
        );
        let shared = patch
            .iter()
            .flatten()
            .copied()
            .find(|d| (0..3).all(|i| (d[i] - truth[i]).abs() < 0.07));
        let shared = shared.expect("the patch's displacement is the ball's");
        let sharing = patch.iter().flatten().filter(|&&d| d == shared).count();
        assert!(sharing >= 4, "{patch:?}");
    }

    /// The banded ball again, its anchors filling it (a grid 0.1 apart inside it at frame 0)
    /// beside floor anchors: each view sees a point inside it on some band, so many have no
    /// colour their cameras agree on, and most of those that do alias a band when searched alone.
    /// Placed by cells, camera by camera, the ball's anchors land where the ball went (within half
    /// a band); the floor's stay; and where the ball is out of reach nothing moves.
    #[test]
    fn the_consensus_places_an_objects_anchors_that_the_search_cannot() {
        const BAND: f32 = 0.14;
        let from = [-0.6, 0.5, 0.0];
        let to = [0.0, 0.72, 0.2];
        let truth: [f32; 3] = std::array::from_fn(|i| to[i] - from[i]);
        let cameras = rig();
        let (reference, on_0): (Vec<Frame>, Vec<Vec<bool>>) = cameras
            .iter()
            .map(|c| render_ball(c, from, Some(BAND)))
            .unzip();
        let (target, on_f): (Vec<Frame>, Vec<Vec<bool>>) = cameras
            .iter()
            .map(|c| render_ball(c, to, Some(BAND)))
            .unzip();
        let masks: Vec<Vec<bool>> = on_0
            .iter()
            .zip(&on_f)
            .map(|(a, b)| a.iter().zip(b).map(|(&a, &b)| a || b).collect())
            .collect();
        let mut anchors: Vec<[f32; 3]> = Vec::new();
        for i in -3..=3 {
            for j in -3..=3 {
                for k in -3..=3 {
                    let o = [i as f32 * 0.1, j as f32 * 0.1, k as f32 * 0.1];
                    if dot(o, o).sqrt() <= BALL_RADIUS {
                        anchors.push(std::array::from_fn(|c| from[c] + o[c]));
                    }
                }
            }
        }
        let on_ball = anchors.len();
        // Floor anchors around the ball's foot and far from it.
        anchors.extend([
            [-0.6, 0.0, 0.4],
            [-0.2, 0.0, 0.0],
            [0.9, 0.0, -0.7],
            [-1.0, 0.0, -0.3],
        ]);
        let reference_refs: Vec<&Frame> = reference.iter().collect();
        let target_refs: Vec<&Frame> = target.iter().collect();
        let reference_views = FrameViews {
            cameras: &cameras,
            images: &reference_refs,
            moving: &masks,
        };
        let target_views = FrameViews {
            cameras: &cameras,
            images: &target_refs,
            moving: &masks,
        };
        let (placements, _) = search_placements(
            &reference_views,
            &anchors,
            &target_views,
            &anchors,
            &vec![true; anchors.len()],
            PARAMS,
        );
        let consensus = |placements: &[Placement]| {
            place_by_consensus(
                &reference_views,
                &anchors,
                &target_views,
                &anchors,
                placements,
                0.3,
                PARAMS,
            )
        };
        let (together, report) = consensus(&placements);
        // Anchors of the ball placed within 0.15 (about half a band) of where it took them.
        let placed = |moves: &[Option<[f32; 3]>]| {
            moves[..on_ball]
                .iter()
                .flatten()
                .filter(|d| distance(**d, truth) < 0.15)
                .count()
        };
        let alone: Vec<Option<[f32; 3]>> = placements
            .iter()
            .map(|p| match p {
                Placement::Moved(d) => Some(*d),
                _ => None,
            })
            .collect();
        let unreliable = placements[..on_ball]
            .iter()
            .filter(|p| **p == Placement::Unreliable)
            .count();
        eprintln!(
            "{on_ball} ball anchors, {unreliable} unreliable; placed alone {}, together {}; {report:?}",
            placed(&alone),
            placed(&together)
        );
        assert!(
            3 * unreliable > on_ball,
            "a third have no colour of their own"
        );
        assert!(
            4 * placed(&alone) < on_ball,
            "alone, most stay behind or alias"
        );
        assert!(
            10 * placed(&together) >= 9 * on_ball,
            "together, nine in ten are placed: {} of {on_ball}",
            placed(&together)
        );
        assert!(report.adopted > 0 && report.corrected > 0, "{report:?}");
        // Hardly any anchor lands off the ball's path (alone, 83 of the 94 moved do): one in
        // twenty at most (6 measured), found anchors whose aliased place no cell's motion beats.
        let off = |moves: &[Option<[f32; 3]>]| {
            moves[..on_ball]
                .iter()
                .flatten()
                .filter(|d| distance(**d, truth) >= 0.15)
                .count()
        };
        assert!(
            20 * off(&together) <= on_ball && off(&alone) > on_ball / 3,
            "{} off the ball's path together, {} alone",
            off(&together),
            off(&alone)
        );
        assert!(
            together[on_ball..].iter().all(Option::is_none),
            "{:?}",
            &together[on_ball..]
        );

        // Negative control: the ball out of the search's reach (3 units away, its pixels that
        // frame's moving ones) shows no motion the cameras confirm, and nothing moves.
        let far = [2.4, 0.5, 0.0];
        let (gone, on_far): (Vec<Frame>, Vec<Vec<bool>>) = cameras
            .iter()
            .map(|c| render_ball(c, far, Some(BAND)))
            .unzip();
        let gone_refs: Vec<&Frame> = gone.iter().collect();
        let gone_views = FrameViews {
            cameras: &cameras,
            images: &gone_refs,
            moving: &on_far,
        };
        let (placements, _) = search_placements(
            &reference_views,
            &anchors,
            &gone_views,
            &anchors,
            &vec![true; anchors.len()],
            PARAMS,
        );
        let (moves, report) = place_by_consensus(
            &reference_views,
            &anchors,
            &gone_views,
            &anchors,
            &placements,
            0.3,
            PARAMS,
        );
        assert_eq!(report, ConsensusReport::default());
        assert!(moves.iter().all(Option::is_none), "{moves:?}");
    }
}
