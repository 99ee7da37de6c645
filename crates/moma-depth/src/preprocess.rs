//! Exact Depth Anything V2 pre- and post-processing (METHOD.md §5), pure functions.
//!
//! CONTRACT (implemented by the candle work item): keep these names and signatures.

use ndarray::{Array2, Array3, ArrayView2};

use crate::error::Result;

/// RGB 8-bit → `(3, H, W)` network input: /255, lower-bound aspect-keeping resize to multiples of 14
/// with OpenCV INTER_CUBIC semantics, ImageNet normalisation.
///
/// # Errors
/// Empty image.
pub fn preprocess(rgb: &image::RgbImage, input_size: usize) -> Result<Array3<f32>> {
    let _ = (rgb, input_size);
    todo!("candle work item")
}

/// Bilinear resize with `align_corners = true` (PyTorch semantics) to `(out_h, out_w)`.
pub fn resize_bilinear_align_corners(src: &ArrayView2<'_, f32>, out_h: usize, out_w: usize) -> Array2<f32> {
    let _ = (src, out_h, out_w);
    todo!("candle work item")
}
