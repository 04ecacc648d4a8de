//! Trajectory coherence (not in GIFStream; docs/results.md, "Moving objects"): anchors of one
//! object should move together.
//!
//! Independent per-anchor trajectories let an object's anchors drift apart. An anchor inside a
//! uniformly coloured region, or one whose object moved out from under it, gets no photometric
//! gradient along the motion (the aperture problem), stays behind, and the object thins out
//! frame by frame. The term pulls each anchor's applied trajectory mf·K towards the mean of its
//! *motion peers*: anchors of the same coarse cell of the canonical (frame-0) space, so the pull
//! reaches across an object at once instead of diffusing through nearest neighbours (a 6-NN
//! version measured no better than none). L1, so an anchor whose own photometric gradient
//! disagrees (an object boundary inside a cell) can still move apart.

use crate::device_io::upload;
use std::collections::HashMap;

use burn::tensor::{Int, Tensor, TensorData, s};

use crate::model::anchor_columns::MOTION_GATE;
use crate::model::inputs::activate_gates;
use crate::raster::gather::gather_rows;

/// Peers per anchor.
pub const MOTION_PEERS: usize = 8;

/// Frames at which `CoherenceGroups::SpaceTime` takes the anchors' cells: the first, the last
/// and three between, evenly. Five because the fastest synthetic objects cross a 0.3 cell in
/// about two frames and turn by at most ~90° between samples, so anchors a sample apart that
/// share all five cells moved together; more samples would split an object's rotating parts
/// into ever smaller groups.
pub const SPACE_TIME_SAMPLES: usize = 5;

/// Steps between regroupings under `CoherenceGroups::SpaceTime`: the trajectories change as
/// they are fitted, but slowly against the ~1,200 dynamic steps of the default run, and each
/// regrouping decodes every anchor at five frames.
pub const SPACE_TIME_REGROUP_EVERY: usize = 100;

/// The frames (0-based, within a clip of `frames`) that `CoherenceGroups::SpaceTime` samples.
pub fn space_time_frames(frames: usize) -> Vec<usize> {
    let last = frames.saturating_sub(1);
    let mut picked: Vec<usize> = (0..SPACE_TIME_SAMPLES)
        .map(|k| ((k * last) as f64 / (SPACE_TIME_SAMPLES - 1) as f64).round() as usize)
        .collect();
    picked.dedup();
    picked
}

/// [N · MOTION_PEERS] motion peers: for each anchor, anchors sharing its cell (cubes of side
/// `cell`) in every one of `tracks` (anchor positions at some frames, one slice per frame;
/// canonical grouping passes the canonical positions alone), spread evenly over the group's
/// members in index order (deterministic, so a resumed run rebuilds the same lists). An anchor
/// alone in its group is its own peer.
pub fn motion_peers(tracks: &[&[[f32; 3]]], cell: f32) -> Vec<u32> {
    let n = tracks.first().map_or(0, |t| t.len());
    assert!(
        tracks.iter().all(|t| t.len() == n),
        "positions of different anchor sets"
    );
    let key = |i: usize| -> Vec<i64> {
        tracks
            .iter()
            .flat_map(|t| t[i].map(|v| (v / cell).floor() as i64))
            .collect()
    };
    let keys: Vec<Vec<i64>> = (0..n).map(key).collect();
    let mut groups: HashMap<&[i64], Vec<u32>> = HashMap::new();
    for (i, k) in keys.iter().enumerate() {
        groups.entry(k.as_slice()).or_default().push(i as u32);
    }
    let mut rank = vec![0usize; n];
    for members in groups.values() {
        for (r, &i) in members.iter().enumerate() {
            rank[i as usize] = r;
        }
    }
    keys.iter()
        .enumerate()
        .flat_map(|(i, k)| {
            let members = &groups[k.as_slice()];
            let len = members.len();
            let stride = (len / (MOTION_PEERS + 1)).max(1);
            let r = rank[i];
            (1..=MOTION_PEERS).map(move |j| members[(r + j * stride) % len])
        })
        .collect()
}

/// [N, W] the applied trajectories mf·K of the trajectory regularisers (this term and
/// `curvature.rs`): the motion gates mf are constants there, since the photometric loss and the
/// gate regulariser decide them.
pub fn gated_trajectory(trajectory: Tensor<2>, factors: Tensor<2>) -> Tensor<2> {
    let gates = activate_gates(factors)
        .slice(s![.., MOTION_GATE..MOTION_GATE + 1])
        .detach();
    trajectory * gates
}

/// Mean over anchors and knot coordinates of |mf·K − mean over the peers of mf·K| (mf·K by
/// [`gated_trajectory`]).
pub fn trajectory_coherence(trajectory: Tensor<2>, factors: Tensor<2>, peers: &[u32]) -> Tensor<1> {
    let [n, w] = trajectory.dims();
    assert_eq!(
        peers.len(),
        n * MOTION_PEERS,
        "peer lists of another anchor set"
    );
    let applied = gated_trajectory(trajectory, factors);
    let index = upload::<1, Int>(
        TensorData::new(
            peers.iter().map(|&j| j as i64).collect::<Vec<_>>(),
            [n * MOTION_PEERS],
        ),
        &applied.device(),
    );
    let mean = gather_rows(applied.clone(), index)
        .reshape([n, MOTION_PEERS, w])
        .mean_dim(1)
        .reshape([n, w]);
    (applied - mean).abs().mean()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peers_stay_in_their_cell_and_cover_it() {
        // Two cells: 20 anchors near the origin, 3 near (1, 1, 1), one alone.
        let mut positions: Vec<[f32; 3]> = (0..20).map(|i| [0.01 * i as f32, 0.0, 0.0]).collect();
        positions.extend((0..3).map(|i| [1.0 + 0.01 * i as f32, 1.0, 1.0]));
        positions.push([5.0, 5.0, 5.0]);
        let peers = motion_peers(&[&positions], 0.5);
        assert_eq!(peers.len(), positions.len() * MOTION_PEERS);
        for (i, list) in peers.chunks(MOTION_PEERS).enumerate() {
            let cell = |p: [f32; 3]| p.map(|v| (v / 0.5).floor() as i64);
            for &j in list {
                assert_eq!(
                    cell(positions[j as usize]),
                    cell(positions[i]),
                    "anchor {i}"
                );
            }
        }
        // The big cell: peers spread over it, not just the next indices.
        let first: Vec<u32> = peers[..MOTION_PEERS].to_vec();
        assert!(first.iter().any(|&j| j >= 10), "{first:?}");
        assert!(!first.contains(&0), "not its own peer in a populated cell");
        // The lone anchor is its own peer.
        assert!(peers[23 * MOTION_PEERS..].iter().all(|&j| j == 23));
        assert_eq!(peers, motion_peers(&[&positions], 0.5), "deterministic");
    }

    #[test]
    fn space_time_groups_split_what_moves_apart() {
        // Eight anchors in one canonical cell: four stay, four move 1 unit along x by the last
        // frame (an object leaving the floor it started on).
        let start: Vec<[f32; 3]> = (0..8).map(|i| [0.05 + 0.02 * i as f32, 0.1, 0.1]).collect();
        let end: Vec<[f32; 3]> = start
            .iter()
            .enumerate()
            .map(|(i, p)| if i < 4 { *p } else { [p[0] + 1.0, p[1], p[2]] })
            .collect();
        let canonical = motion_peers(&[&start], 0.3);
        let space_time = motion_peers(&[&start, &end], 0.3);
        let mixed = |peers: &[u32]| {
            peers
                .chunks(MOTION_PEERS)
                .enumerate()
                .any(|(i, list)| list.iter().any(|&j| (j < 4) != (i < 4)))
        };
        assert!(mixed(&canonical), "one canonical cell mixes them");
        assert!(
            !mixed(&space_time),
            "space-time groups never do: {space_time:?}"
        );
        // Motion within a cell does not split a group.
        let jitter: Vec<[f32; 3]> = start.iter().map(|p| [p[0] + 0.01, p[1], p[2]]).collect();
        assert_eq!(motion_peers(&[&start, &jitter], 0.3), canonical);
    }

    #[test]
    fn space_time_frames_span_the_clip() {
        assert_eq!(space_time_frames(40), vec![0, 10, 20, 29, 39]);
        assert_eq!(space_time_frames(3), vec![0, 1, 2]);
        assert_eq!(space_time_frames(1), vec![0]);
    }
}
