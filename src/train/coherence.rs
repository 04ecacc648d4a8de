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

use crate::model::inputs::activate_gates;
use crate::raster::gather::gather_rows;

/// Peers per anchor.
pub const MOTION_PEERS: usize = 8;

/// [N · MOTION_PEERS] motion peers: for each anchor, anchors of its cell (cubes of side `cell`
/// in canonical space), spread evenly over the cell's members in index order (deterministic, so
/// a resumed run rebuilds the same lists). An anchor alone in its cell is its own peer.
pub fn motion_peers(positions: &[[f32; 3]], cell: f32) -> Vec<u32> {
    let key = |p: &[f32; 3]| p.map(|v| (v / cell).floor() as i64);
    let mut cells: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
    for (i, p) in positions.iter().enumerate() {
        cells.entry(key(p)).or_default().push(i as u32);
    }
    let mut rank = vec![0usize; positions.len()];
    for members in cells.values() {
        for (r, &i) in members.iter().enumerate() {
            rank[i as usize] = r;
        }
    }
    positions
        .iter()
        .enumerate()
        .flat_map(|(i, p)| {
            let members = &cells[&key(p)];
            let len = members.len();
            let stride = (len / (MOTION_PEERS + 1)).max(1);
            let r = rank[i];
            (1..=MOTION_PEERS).map(move |j| members[(r + j * stride) % len])
        })
        .collect()
}

/// Mean over anchors and knot coordinates of |mf·K − mean over the peers of mf·K|; the gates
/// are constants here (the photometric loss and the gate regulariser decide them).
pub fn trajectory_coherence(trajectory: Tensor<2>, factors: Tensor<2>, peers: &[u32]) -> Tensor<1> {
    let [n, w] = trajectory.dims();
    assert_eq!(
        peers.len(),
        n * MOTION_PEERS,
        "peer lists of another anchor set"
    );
    let gates = activate_gates(factors).slice(s![.., 1..2]).detach();
    let applied = trajectory * gates;
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
        let peers = motion_peers(&positions, 0.5);
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
        assert_eq!(peers, motion_peers(&positions, 0.5), "deterministic");
    }
}
