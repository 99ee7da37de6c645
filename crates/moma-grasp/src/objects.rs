//! Object pixels and their 8-connected components.

use moma_core::Mask;
pub use moma_core::image::components_8;
use ndarray::Array2;

/// Trials of the proxy evaluation (docs/method.md §8): a mask component smaller than this is a speck,
/// not an object. Pixels.
pub const MIN_TRIAL_COMPONENT_PX: usize = 200;

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
