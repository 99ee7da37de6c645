//! Object pixels and their 8-connected components.

use moma_core::{ImageSize, Mask};
use ndarray::Array2;

/// Trials of the proxy evaluation (docs/method.md §8): a mask component smaller than this is a speck,
/// not an object. Pixels.
pub const MIN_TRIAL_COMPONENT_PX: usize = 200;

/// 8-connected components of `pixels` (row-major, `size`): `(labels, counts)` with label 0 for
/// background and labels `1..=counts.len()` in raster order of each component's first pixel;
/// `counts[l - 1]` is the pixel count of label `l`.
pub fn components_8(pixels: &[bool], size: ImageSize) -> (Vec<u32>, Vec<usize>) {
    let (w, h) = (size.width, size.height);
    let mut labels = vec![0u32; pixels.len()];
    let mut counts = Vec::new();
    let mut stack = Vec::new();
    for start in 0..pixels.len() {
        if !pixels[start] || labels[start] != 0 {
            continue;
        }
        let label = counts.len() as u32 + 1;
        labels[start] = label;
        stack.push(start);
        let mut count = 0usize;
        while let Some(i) = stack.pop() {
            count += 1;
            let (u, v) = (i % w, i / w);
            for nv in v.saturating_sub(1)..=(v + 1).min(h - 1) {
                for nu in u.saturating_sub(1)..=(u + 1).min(w - 1) {
                    let j = nv * w + nu;
                    if pixels[j] && labels[j] == 0 {
                        labels[j] = label;
                        stack.push(j);
                    }
                }
            }
        }
        counts.push(count);
    }
    (labels, counts)
}

/// The trials of a mask: one [`Mask`] per 8-connected component with at least `min_px` pixels
/// (use [`MIN_TRIAL_COMPONENT_PX`]), in raster order of their first pixel.
pub fn mask_components(mask: &Mask, min_px: usize) -> Vec<Mask> {
    let size = mask.size();
    let flat: Vec<bool> = mask.data().iter().copied().collect();
    let (labels, counts) = components_8(&flat, size);
    counts
        .iter()
        .enumerate()
        .filter(|(_, c)| **c >= min_px)
        .map(|(k, _)| {
            let l = k as u32 + 1;
            let data =
                Array2::from_shape_fn(size.shape(), |(v, u)| labels[v * size.width + u] == l);
            Mask::new(data)
        })
        .collect()
}
