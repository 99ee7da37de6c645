//! RGB → the grey the anchor rule of re-alignment compares ([`moma_core::realign::GreyHalf`]):
//! the image conversion lives with the images, the rule that uses it in moma-core.

use moma_core::realign::GreyHalf;
use moma_core::{CoreError, ImageSize};
use ndarray::{Array2, ArrayView3};

/// Grey g = (R + 2G + B)/4 averaged over 2×2 blocks, as f32 in [0, 255], at half resolution
/// (half-resolution pixel (i, j) covers full-resolution rows 2i, 2i+1 and columns 2j, 2j+1; an
/// odd last row or column is dropped), of an RGB image `(height, width, 3)` in any layout.
///
/// # Errors
/// [`CoreError::InvalidParameter`] for a channel count other than 3.
pub fn grey_half(rgb: ArrayView3<'_, u8>) -> moma_core::Result<GreyHalf> {
    let (h, w, c) = rgb.dim();
    if c != 3 {
        return Err(CoreError::InvalidParameter(format!(
            "an RGB image must have 3 channels, got {c}"
        )));
    }
    let (hh, hw) = (h / 2, w / 2);
    let owned;
    let data: &[u8] = match rgb.as_slice() {
        Some(s) => s,
        None => {
            owned = rgb.iter().copied().collect::<Vec<u8>>();
            &owned
        }
    };
    let stride = 3 * w;
    let mut out = Vec::with_capacity(hh * hw);
    for i in 0..hh {
        let r0 = &data[2 * i * stride..2 * i * stride + 6 * hw];
        let r1 = &data[(2 * i + 1) * stride..(2 * i + 1) * stride + 6 * hw];
        out.extend(r0.chunks_exact(6).zip(r1.chunks_exact(6)).map(|(a, b)| {
            let s = a[0] as u32
                + 2 * a[1] as u32
                + a[2] as u32
                + a[3] as u32
                + 2 * a[4] as u32
                + a[5] as u32
                + b[0] as u32
                + 2 * b[1] as u32
                + b[2] as u32
                + b[3] as u32
                + 2 * b[4] as u32
                + b[5] as u32;
            s as f32 / 16.0
        }));
    }
    let values = Array2::from_shape_vec((hh, hw), out)
        .map_err(|e| CoreError::InvalidParameter(e.to_string()))?;
    GreyHalf::new(ImageSize::new(w, h), values)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The block mean of (R + 2G + B)/4, against a direct per-pixel computation, in a
    /// non-contiguous layout too.
    #[test]
    fn grey_is_the_block_mean_of_the_weighted_channels() {
        let (h, w) = (5, 7);
        let rgb = ndarray::Array3::from_shape_fn((h, w, 3), |(v, u, c)| {
            ((v * 31 + u * 17 + c * 89) % 256) as u8
        });
        let g = grey_half(rgb.view()).unwrap();
        assert_eq!(g.size(), ImageSize::new(7, 5));
        assert_eq!(g.values().dim(), (2, 3));
        let px = |v: usize, u: usize| {
            (rgb[[v, u, 0]] as f32 + 2.0 * rgb[[v, u, 1]] as f32 + rgb[[v, u, 2]] as f32) / 4.0
        };
        for i in 0..2 {
            for j in 0..3 {
                let want = (px(2 * i, 2 * j)
                    + px(2 * i, 2 * j + 1)
                    + px(2 * i + 1, 2 * j)
                    + px(2 * i + 1, 2 * j + 1))
                    / 4.0;
                assert_eq!(g.values()[[i, j]], want);
            }
        }
        let mut transposed = ndarray::Array3::<u8>::zeros((w, h, 3));
        transposed.assign(&rgb.view().permuted_axes([1, 0, 2]));
        let view = transposed.view().permuted_axes([1, 0, 2]);
        assert!(view.as_slice().is_none());
        assert_eq!(grey_half(view).unwrap(), g);
        let e = grey_half(ndarray::Array3::<u8>::zeros((4, 4, 4)).view()).unwrap_err();
        assert!(e.to_string().contains("3 channels"), "{e}");
    }
}
