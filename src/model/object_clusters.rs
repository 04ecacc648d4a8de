//! Moving objects as groups of anchors: single-linkage clusters of the anchors on something
//! moving. Used by the rigid fit when a knot opens (`train/rigid_fit.rs`, on the places at the
//! previous knot's frame) and by the turns derived per object (`model/path_turns.rs`, on the
//! paths, which the decoder derives alike, so the clustering lives with the model).

use std::collections::HashMap;

/// Groups the anchors with `candidate[a]` into objects: two belong together when their
/// `positions` lie within `link` of each other (single linkage); groups of fewer than
/// `min_members` are dropped. Members in ascending order, groups by their first member.
pub fn object_clusters(
    positions: &[[f32; 3]],
    candidate: &[bool],
    link: f32,
    min_members: usize,
) -> Vec<Vec<usize>> {
    object_clusters_linked(positions, candidate, link, min_members, |_, _| true)
}

/// [`object_clusters`] where two candidates within `link` of each other belong together only
/// if `also_linked(a, b)` (a < b) holds too: the turns derived per object
/// (`model/path_turns.rs`) join anchors whose paths stay together, not merely whose canonical
/// places are near.
pub fn object_clusters_linked(
    positions: &[[f32; 3]],
    candidate: &[bool],
    link: f32,
    min_members: usize,
    also_linked: impl Fn(usize, usize) -> bool,
) -> Vec<Vec<usize>> {
    assert_eq!(positions.len(), candidate.len());
    assert!(link > 0.0, "the link distance must be positive");
    let key = |p: &[f32; 3]| p.map(|v| (v / link).floor() as i64);
    let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (a, p) in positions.iter().enumerate() {
        if candidate[a] {
            cells.entry(key(p)).or_default().push(a);
        }
    }
    let mut parent: Vec<usize> = (0..positions.len()).collect();
    fn root(parent: &mut [usize], mut a: usize) -> usize {
        while parent[a] != a {
            parent[a] = parent[parent[a]];
            a = parent[a];
        }
        a
    }
    let link2 = link * link;
    for (a, p) in positions.iter().enumerate() {
        if !candidate[a] {
            continue;
        }
        let k = key(p);
        for o in 0..27 {
            let off = [o % 3 - 1, (o / 3) % 3 - 1, o / 9 - 1];
            let Some(others) = cells.get(&[k[0] + off[0], k[1] + off[1], k[2] + off[2]]) else {
                continue;
            };
            for &b in others {
                if b <= a {
                    continue;
                }
                let q = positions[b];
                let d2: f32 = (0..3).map(|i| (p[i] - q[i]).powi(2)).sum();
                if d2 <= link2 && also_linked(a, b) {
                    let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
                    if ra != rb {
                        parent[ra.max(rb)] = ra.min(rb);
                    }
                }
            }
        }
    }
    let mut groups: HashMap<usize, Vec<usize>> = HashMap::new();
    for a in (0..positions.len()).filter(|&a| candidate[a]) {
        let r = root(&mut parent, a);
        groups.entry(r).or_default().push(a);
    }
    let mut groups: Vec<Vec<usize>> = groups
        .into_values()
        .filter(|g| g.len() >= min_members)
        .collect();
    groups.sort_by_key(|g| g[0]);
    groups
}

/// Whether anchors `a` and `b` moved as one body from `earlier` to `now`: both travelled at
/// least `travelled` and their distance changed by at most `tolerance` (a rigid motion keeps
/// every distance). Two pieces of one object that the places alone do not link (a gap wider than
/// the link, where the cameras see no moving pixels) are linked by it, while a slow or still
/// neighbour, or an object passing by in another direction, is not. The rigid fit's
/// `train.rigid_fit_grouping = "kept-distances"`.
pub fn moved_as_one(
    earlier: &[[f32; 3]],
    now: &[[f32; 3]],
    a: usize,
    b: usize,
    travelled: f32,
    tolerance: f32,
) -> bool {
    let length = |p: [f32; 3], q: [f32; 3]| (0..3).map(|i| (p[i] - q[i]).powi(2)).sum::<f32>().sqrt();
    length(earlier[a], now[a]) >= travelled
        && length(earlier[b], now[b]) >= travelled
        && (length(now[a], now[b]) - length(earlier[a], earlier[b])).abs() <= tolerance
}

/// The rigid fit's objects under `train.rigid_fit_grouping = "kept-distances"`: the candidates
/// within `link` of each other at `now`, and also those within twice that which moved as one
/// body from `earlier` ([`moved_as_one`]: both travelled a link and kept their distance to half
/// of one). On `crossing` the flying cube travels 0.3-0.45 per knot interval, the slow objects
/// beside it 0.04-0.07 (a longer link alone joined them to it).
pub fn clusters_moved_as_one(
    now: &[[f32; 3]],
    earlier: &[[f32; 3]],
    candidate: &[bool],
    link: f32,
    min_members: usize,
) -> Vec<Vec<usize>> {
    object_clusters_linked(now, candidate, 2.0 * link, min_members, |a, b| {
        let (p, q) = (now[a], now[b]);
        let d2: f32 = (0..3).map(|i| (p[i] - q[i]).powi(2)).sum();
        d2 <= link * link || moved_as_one(earlier, now, a, b, link, 0.5 * link)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pieces_that_moved_as_one_body_join_and_their_neighbours_do_not() {
        // Two pieces of one body (lines of anchors 0.1 apart, a gap of 0.25 between them) turned
        // 18° about z and shifted 0.4 along x; beside them a slow piece (0.02 along x) and a
        // piece that moved as far, the other way, each 0.25 from the body.
        let turn = glam::Quat::from_rotation_z(18f32.to_radians());
        let mut earlier: Vec<[f32; 3]> = Vec::new();
        let mut now: Vec<[f32; 3]> = Vec::new();
        let mut add = |p: glam::Vec3, q: glam::Vec3| {
            earlier.push(p.to_array());
            now.push(q.to_array());
        };
        let body = |p: glam::Vec3| turn * p + glam::Vec3::new(0.4, 0.0, 0.0);
        for i in 0..5 {
            let p = glam::Vec3::new(i as f32 * 0.1, 0.0, 0.0);
            add(p, body(p));
        }
        for i in 0..5 {
            let p = glam::Vec3::new(0.65 + i as f32 * 0.1, 0.0, 0.0);
            add(p, body(p));
        }
        for i in 0..5 {
            let p = glam::Vec3::new(i as f32 * 0.1, 0.25, 0.0);
            add(p, p + glam::Vec3::new(0.02, 0.0, 0.0));
        }
        for i in 0..5 {
            let p = glam::Vec3::new(0.65 + i as f32 * 0.1, -0.25, 0.0);
            add(p, p + glam::Vec3::new(-0.4, 0.0, 0.0));
        }
        // Grouped where they stand now (the rigid fit's previous frame).
        let (link, candidate) = (0.15, vec![true; 20]);
        let near = object_clusters(&now, &candidate, link, 3);
        assert_eq!(near.len(), 4, "{near:?}");
        let joined = clusters_moved_as_one(&now, &earlier, &candidate, link, 3);
        assert_eq!(
            joined,
            vec![(0..10).collect::<Vec<_>>(), (10..15).collect(), (15..20).collect()]
        );
        // The rule itself: a body's anchors keep their distance, a slow one never travelled.
        assert!(moved_as_one(&earlier, &now, 0, 9, 0.15, 0.001));
        assert!(!moved_as_one(&earlier, &now, 0, 10, 0.15, 0.075));
        assert!(!moved_as_one(&earlier, &now, 9, 19, 0.15, 0.075));
    }

    #[test]
    fn clusters_join_anchors_within_the_link_and_drop_small_groups() {
        // Two lines of anchors 0.1 apart, 1.0 from each other, and a pair.
        let mut positions = Vec::new();
        for i in 0..10 {
            positions.push([i as f32 * 0.1, 0.0, 0.0]);
        }
        for i in 0..6 {
            positions.push([i as f32 * 0.1, 1.0, 0.0]);
        }
        positions.push([5.0, 5.0, 5.0]);
        positions.push([5.05, 5.0, 5.0]);
        let mut candidate = vec![true; positions.len()];
        let groups = object_clusters(&positions, &candidate, 0.15, 3);
        assert_eq!(
            groups,
            vec![(0..10).collect::<Vec<_>>(), (10..16).collect()]
        );
        // A non-candidate breaks a chain.
        candidate[5] = false;
        let groups = object_clusters(&positions, &candidate, 0.15, 3);
        assert_eq!(
            groups,
            vec![vec![0, 1, 2, 3, 4], vec![6, 7, 8, 9], (10..16).collect()]
        );
    }

    #[test]
    fn a_further_link_condition_splits_what_distance_alone_joins() {
        // One line of anchors 0.1 apart whose two halves part ways: linked only within a half.
        let positions: Vec<[f32; 3]> = (0..10).map(|i| [i as f32 * 0.1, 0.0, 0.0]).collect();
        let candidate = vec![true; positions.len()];
        let half = |a: usize| a < 5;
        let groups =
            object_clusters_linked(&positions, &candidate, 0.15, 3, |a, b| half(a) == half(b));
        assert_eq!(groups, vec![(0..5).collect::<Vec<_>>(), (5..10).collect()]);
        assert_eq!(
            object_clusters(&positions, &candidate, 0.15, 3),
            vec![(0..10).collect::<Vec<_>>()]
        );
    }
}
