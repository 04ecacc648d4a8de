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

#[cfg(test)]
mod tests {
    use super::*;

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
