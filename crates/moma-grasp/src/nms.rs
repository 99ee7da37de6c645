//! Seeded subsampling, ranking and greedy non-maximum suppression.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// At most `max` items of `items`, chosen uniformly with `seed` (partial Fisher–Yates), returned in
/// their original order. All items when `items.len() <= max`.
pub fn subsample<T: Copy + Ord>(mut items: Vec<T>, max: usize, seed: u64) -> Vec<T> {
    if items.len() <= max {
        return items;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for k in 0..max {
        let j = rng.random_range(k..items.len());
        items.swap(k, j);
    }
    items.truncate(max);
    items.sort_unstable();
    items
}

/// Indices of `scores` sorted best first; ties keep the original order (deterministic).
pub fn rank(scores: &[f32]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    order
}

/// Greedy NMS: walks `order`, calls `accept(i)` (a final check that may reject), keeps `i` unless
/// `suppress(kept, i)` is true for an already kept item, and stops at `top_k` kept.
pub fn greedy<F, G>(order: &[usize], top_k: usize, mut accept: F, suppress: G) -> Vec<usize>
where
    F: FnMut(usize) -> bool,
    G: Fn(usize, usize) -> bool,
{
    // `top_k` comes from the user (`--top`): never more room than there are items.
    let mut kept: Vec<usize> = Vec::with_capacity(top_k.min(order.len()));
    for &i in order {
        if kept.len() >= top_k {
            break;
        }
        if kept.iter().any(|&k| suppress(k, i)) {
            continue;
        }
        if accept(i) {
            kept.push(i);
        }
    }
    kept
}
