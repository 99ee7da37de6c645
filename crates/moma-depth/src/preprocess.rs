//! Exact Depth Anything V2 pre- and post-processing (docs/method.md §5), pure functions.
//!
//! The official pipeline (`depth_anything_v2/dpt.py::image2tensor`, commit a561b84) is
//!
//! ```text
//! image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) / 255.0          # float64
//! Resize(518, 518, keep_aspect_ratio=True, ensure_multiple_of=14,
//!        resize_method="lower_bound", image_interpolation_method=cv2.INTER_CUBIC)
//! NormalizeImage(mean=[0.485, 0.456, 0.406], std=[0.229, 0.224, 0.225])
//! PrepareForNet()                                                 # HWC -> CHW, float32
//! ...
//! depth = F.interpolate(depth[:, None], (h, w), mode="bilinear", align_corners=True)
//! ```
//!
//! [`preprocess`] reproduces the first four lines (OpenCV's `INTER_CUBIC` on a float image:
//! Keys kernel a = −0.75 with weights computed in `f32`, pixel centres at +0.5, replicated
//! borders, no antialiasing; arithmetic in `f64` as on NumPy's float64 image), and
//! [`resize_bilinear_align_corners`] the last one.
//!
//! CONTRACT: keep these names and signatures (other backends call them).

use moma_core::ImageSize;
use ndarray::{Array2, Array3, ArrayView2};
use rayon::prelude::*;

use crate::error::{DepthError, Result};

/// Patch size of the DINOv2 backbone: network input sides are multiples of it
/// (`Resize(ensure_multiple_of=14)` in `depth_anything_v2/dpt.py`).
pub const PATCH_SIZE: usize = 14;

/// Default lower bound of both network-input sides, pixels (`input_size=518` in `dpt.py::infer_image`).
pub const DEFAULT_INPUT_SIZE: usize = 518;

/// ImageNet channel means (R, G, B) of `NormalizeImage` in `dpt.py::image2tensor`.
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];

/// ImageNet channel standard deviations (R, G, B) of `NormalizeImage` in `dpt.py::image2tensor`.
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];

/// Keys' cubic-convolution parameter used by OpenCV's `INTER_CUBIC` (`interpolateCubic`, `A = -0.75f`)
/// and by PyTorch's bicubic `interpolate`.
pub const CUBIC_A: f32 = -0.75;

/// Network input size of the official `Resize(lower_bound, ensure_multiple_of=14)` for an image of
/// `image` pixels and lower bound `input_size` (pixels).
///
/// Scale = max(input_size / h, input_size / w) (both sides ≥ the bound); each scaled side is rounded
/// to the nearest multiple of [`PATCH_SIZE`] (ties to even, as `np.round`), or rounded up when that
/// falls below `input_size`. 480×640 (h×w) at 518 → 518×686; at 392 → 392×518.
///
/// # Errors
/// [`DepthError::Shape`] for an empty image, an `input_size` of 0 or over
/// [`MAX_INPUT_SIZE_PX`], or a network input over [`MAX_NETWORK_INPUT_PIXELS`].
///
/// ```
/// use moma_core::ImageSize;
/// use moma_depth::preprocess::network_input_size;
/// let s = network_input_size(ImageSize::new(640, 480), 518).unwrap();
/// assert_eq!((s.height, s.width), (518, 686));
/// ```
pub fn network_input_size(image: ImageSize, input_size: usize) -> Result<ImageSize> {
    // Any lower bound, as the official `Resize` (the user-facing options also ask for a multiple
    // of 14: [`check_input_size`]), but bounded.
    if input_size > MAX_INPUT_SIZE_PX {
        return Err(DepthError::Shape(format!(
            "input size {input_size} px is above the limit of {MAX_INPUT_SIZE_PX} px"
        )));
    }
    if image.width == 0 || image.height == 0 || input_size == 0 {
        return Err(DepthError::Shape(format!(
            "cannot resize a {}x{} image to lower bound {input_size}",
            image.width, image.height
        )));
    }
    let target = input_size as f64;
    let mut scale_h = target / image.height as f64;
    let mut scale_w = target / image.width as f64;
    // `get_size`: "scale such that output size is lower bound".
    if scale_w > scale_h {
        scale_h = scale_w;
    } else {
        scale_w = scale_h;
    }
    let constrain = |x: f64| -> usize {
        let m = PATCH_SIZE as f64;
        let y = (x / m).round_ties_even() * m;
        let y = if y < target { (x / m).ceil() * m } else { y };
        y as usize
    };
    let size = ImageSize::new(
        constrain(scale_w * image.width as f64),
        constrain(scale_h * image.height as f64),
    );
    // the transformer's attention grows as the square of the patches: a 2×3000 image at 112 px
    // (a 112×168 000 input, 96 000 patches) ran for minutes at 1 GB and more before this
    let (short, long) = (size.width.min(size.height), size.width.max(size.height));
    if long > MAX_NETWORK_ASPECT * short {
        return Err(DepthError::Shape(format!(
            "a {}x{} image at lower bound {input_size} px needs a {size} network input, longer \
             than {MAX_NETWORK_ASPECT} times its short side: its aspect ratio is too extreme for \
             a depth model (crop the image)",
            image.width, image.height
        )));
    }
    if size.pixels() > MAX_NETWORK_INPUT_PIXELS {
        return Err(DepthError::Shape(format!(
            "a {}x{} image at lower bound {input_size} px needs a {size} network input, more than \
             {MAX_NETWORK_INPUT_PIXELS} pixels: its aspect ratio is too extreme for this input \
             size (crop the image, or lower --input-size)",
            image.width, image.height
        )));
    }
    Ok(size)
}

/// Largest network input lower bound accepted, pixels (300 patches of 14; the released models
/// use 518). Far larger bounds only exhaust memory: 14 000 px took 12.5 GB with a 4-layer test
/// network before it was refused.
pub const MAX_INPUT_SIZE_PX: usize = 4200;

/// Largest ratio of the network input's long side to its short side (a panorama of 4:1; the
/// released models were trained on camera images of 4:3 to 16:9).
pub const MAX_NETWORK_ASPECT: usize = 4;

/// Largest network input accepted, pixels (a 2:1 image at [`MAX_INPUT_SIZE_PX`]): bounds the
/// memory of an image whose aspect ratio makes the long side huge at the given lower bound.
pub const MAX_NETWORK_INPUT_PIXELS: usize = 2 * MAX_INPUT_SIZE_PX * MAX_INPUT_SIZE_PX;

/// Checks a network input lower bound: a positive multiple of 14 pixels, at most
/// [`MAX_INPUT_SIZE_PX`].
///
/// # Errors
/// [`DepthError::Shape`] naming the value and the rule.
pub fn check_input_size(input_size: usize) -> Result<()> {
    if input_size == 0 || !input_size.is_multiple_of(PATCH_SIZE) || input_size > MAX_INPUT_SIZE_PX {
        return Err(DepthError::Shape(format!(
            "input size {input_size} px must be a positive multiple of {PATCH_SIZE} and at most \
             {MAX_INPUT_SIZE_PX} (the released models use 518)"
        )));
    }
    Ok(())
}

/// RGB 8-bit → `(3, H, W)` network input: /255, lower-bound aspect-keeping resize to multiples of 14
/// with OpenCV INTER_CUBIC semantics, ImageNet normalisation.
///
/// `input_size` is the lower bound of both sides in pixels (518 for the released models); the output
/// size is [`network_input_size`]. Channel order R, G, B; values `(x/255 − mean) / std`.
///
/// # Errors
/// Empty image.
///
/// ```
/// let rgb = image::RgbImage::from_pixel(64, 48, image::Rgb([128, 64, 32]));
/// let x = moma_depth::preprocess::preprocess(&rgb, 518).unwrap();
/// assert_eq!(x.shape(), &[3, 518, 686]);
/// ```
pub fn preprocess(rgb: &image::RgbImage, input_size: usize) -> Result<Array3<f32>> {
    let src_size = ImageSize::new(rgb.width() as usize, rgb.height() as usize);
    let dst_size = network_input_size(src_size, input_size)?;
    let (h, w) = dst_size.shape();
    let mut out = vec![0.0f32; 3 * h * w];
    resize_cubic_opencv_normalise(rgb.as_raw(), src_size, dst_size, &mut out);
    Array3::from_shape_vec((3, h, w), out)
        .map_err(|e| DepthError::Shape(format!("pre-processed image: {e}")))
}

/// OpenCV `interpolateCubic` (imgproc/src/resize.cpp): the four Keys weights, computed in `f32`,
/// for taps at offsets −1, 0, 1, 2 from `floor(src)`, `x = src − floor(src)` in `[0, 1)`.
fn opencv_cubic_weights(x: f32) -> [f32; 4] {
    let a = CUBIC_A;
    let c0 = ((a * (x + 1.0) - 5.0 * a) * (x + 1.0) + 8.0 * a) * (x + 1.0) - 4.0 * a;
    let c1 = ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0;
    let c2 = ((a + 2.0) * (1.0 - x) - (a + 3.0)) * (1.0 - x) * (1.0 - x) + 1.0;
    let c3 = 1.0 - c0 - c1 - c2;
    [c0, c1, c2, c3]
}

/// Source taps (clamped indices, replicated border) and weights of OpenCV `INTER_CUBIC` along one
/// axis: `fx = (float)((dx + 0.5) * scale − 0.5)`, `scale = src / dst` in `f64`.
fn opencv_cubic_taps(src_len: usize, dst_len: usize) -> Vec<([usize; 4], [f32; 4])> {
    // cv::resize: inv_scale = (double)dsize/ssize; scale = 1/inv_scale.
    let scale = 1.0 / (dst_len as f64 / src_len as f64);
    let last = src_len as i64 - 1;
    (0..dst_len)
        .map(|d| {
            let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let s = f.floor();
            let frac = f - s;
            let s = s as i64;
            let idx = [s - 1, s, s + 1, s + 2].map(|i| i.clamp(0, last) as usize);
            (idx, opencv_cubic_weights(frac))
        })
        .collect()
}

/// OpenCV `cv2.resize(img, (dst.width, dst.height), interpolation=cv2.INTER_CUBIC)` of the 8-bit
/// RGB image `src` (row-major HWC) taken as `f64` in `[0, 1]` (`v / 255`, as the official code's
/// `image / 255.0`), then `(v − mean) / std` per channel, into `out` as `(3, H, W)` `f32`:
/// horizontal pass then vertical pass, `f32` weights, `f64` sums in OpenCV's order (bit-exact
/// against the reference input). Rows run in parallel; every value is computed exactly as in a
/// serial loop.
fn resize_cubic_opencv_normalise(
    src: &[u8],
    src_size: ImageSize,
    dst_size: ImageSize,
    out: &mut [f32],
) {
    let (sh, sw) = src_size.shape();
    let (dh, dw) = dst_size.shape();
    let xt = opencv_cubic_taps(sw, dw);
    let yt = opencv_cubic_taps(sh, dh);
    // `v / 255` for every byte value, the same f64 as computing it in place.
    let unit: [f64; 256] = std::array::from_fn(|v| v as f64 / 255.0);
    // Horizontal pass over every source row: (sh, dw, 3).
    let mut tmp = vec![0.0f64; sh * dw * 3];
    tmp.par_chunks_mut(dw * 3).enumerate().for_each(|(y, out)| {
        let row = &src[y * sw * 3..(y + 1) * sw * 3];
        for ((idx, wt), o) in xt.iter().zip(out.chunks_exact_mut(3)) {
            for (c, o) in o.iter_mut().enumerate() {
                let mut v = 0.0f64;
                for k in 0..4 {
                    v += unit[usize::from(row[idx[k] * 3 + c])] * f64::from(wt[k]);
                }
                *o = v;
            }
        }
    });
    // Vertical pass and normalisation, one output row of the three planes per task.
    let (p0, rest) = out.split_at_mut(dh * dw);
    let (p1, p2) = rest.split_at_mut(dh * dw);
    p0.par_chunks_mut(dw)
        .zip(p1.par_chunks_mut(dw))
        .zip(p2.par_chunks_mut(dw))
        .zip(yt.par_iter())
        .for_each(|(((r0, r1), r2), (idx, wt))| {
            let rows = idx.map(|i| &tmp[i * dw * 3..(i + 1) * dw * 3]);
            let b = wt.map(f64::from);
            let mut planes = [r0, r1, r2];
            for x in 0..dw {
                for (c, plane) in planes.iter_mut().enumerate() {
                    let i = x * 3 + c;
                    let v = rows[0][i] * b[0]
                        + rows[1][i] * b[1]
                        + rows[2][i] * b[2]
                        + rows[3][i] * b[3];
                    plane[x] = ((v - IMAGENET_MEAN[c]) / IMAGENET_STD[c]) as f32;
                }
            }
        });
}

/// Source index pair and weights of PyTorch's `align_corners = true` linear interpolation along one
/// axis: `src = dst · (in − 1)/(out − 1)` (0 when `out = 1`), computed in `f32` as PyTorch does.
pub(crate) fn align_corners_taps(in_len: usize, out_len: usize) -> Vec<(usize, usize, f32, f32)> {
    let scale = if out_len > 1 {
        (in_len as f32 - 1.0) / (out_len as f32 - 1.0)
    } else {
        0.0
    };
    (0..out_len)
        .map(|d| {
            let src = scale * d as f32;
            let i0 = (src as usize).min(in_len - 1);
            let i1 = (i0 + 1).min(in_len - 1);
            let l1 = src - i0 as f32;
            (i0, i1, 1.0 - l1, l1)
        })
        .collect()
}

/// Bilinear resize with `align_corners = true` (PyTorch semantics) to `(out_h, out_w)`.
///
/// `F.interpolate(x[None, None], (out_h, out_w), mode="bilinear", align_corners=True)`: corner pixels
/// map onto corner pixels, `src = dst · (in − 1)/(out − 1)` per axis. An empty source or target gives
/// an empty `(out_h, out_w)` map (zeros when only the source is empty).
///
/// ```
/// use ndarray::array;
/// let a = array![[0.0f32, 1.0], [2.0, 3.0]];
/// let b = moma_depth::preprocess::resize_bilinear_align_corners(&a.view(), 3, 3);
/// assert_eq!(b, array![[0.0, 0.5, 1.0], [1.0, 1.5, 2.0], [2.0, 2.5, 3.0]]);
/// ```
pub fn resize_bilinear_align_corners(
    src: &ArrayView2<'_, f32>,
    out_h: usize,
    out_w: usize,
) -> Array2<f32> {
    let (ih, iw) = src.dim();
    if ih == 0 || iw == 0 {
        return Array2::zeros((out_h, out_w));
    }
    let yt = align_corners_taps(ih, out_h);
    let xt = align_corners_taps(iw, out_w);
    // Row-major source rows as slices (a copy only for a non-standard layout).
    let flat: std::borrow::Cow<'_, [f32]> = match src.as_slice() {
        Some(s) => s.into(),
        None => src.iter().copied().collect::<Vec<_>>().into(),
    };
    let mut out = Array2::zeros((out_h, out_w));
    out.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .zip(yt.par_iter())
        .for_each(|(mut row, &(y0, y1, hy0, hy1))| {
            let (r0, r1) = (&flat[y0 * iw..(y0 + 1) * iw], &flat[y1 * iw..(y1 + 1) * iw]);
            for (o, &(x0, x1, wx0, wx1)) in row.iter_mut().zip(&xt) {
                *o = hy0 * (wx0 * r0[x0] + wx1 * r0[x1]) + hy1 * (wx0 * r1[x0] + wx1 * r1[x1]);
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn size_hw(h: usize, w: usize, bound: usize) -> (usize, usize) {
        network_input_size(ImageSize::new(w, h), bound)
            .unwrap()
            .shape()
    }

    #[test]
    fn size_rule_matches_official_resize() {
        // Depth Anything V2 `Resize.get_size` (lower_bound, multiple of 14).
        assert_eq!(size_hw(480, 640, 518), (518, 686));
        assert_eq!(size_hw(640, 480, 518), (686, 518));
        assert_eq!(size_hw(480, 640, 392), (392, 518));
        assert_eq!(size_hw(518, 518, 518), (518, 518));
        assert_eq!(size_hw(100, 100, 518), (518, 518));
        assert_eq!(size_hw(720, 1280, 518), (518, 924)); // 920.9 -> 65.78*14 -> 66*14
        // 1000×1010 at 518: scale 0.518, w = 523.18 -> 37.37 -> 37*14 = 518 (>= 518, kept).
        assert_eq!(size_hw(1000, 1010, 518), (518, 518));
        // Ties to even: h = 392 (bound), w = 511 -> 511/14 = 36.5 -> np.round -> 36 -> 504.
        assert_eq!(size_hw(392, 511, 392), (392, 504));
        // x/14 = 37.5 -> 38 (even) -> 532.
        assert_eq!(size_hw(392, 525, 392), (392, 532));
        // A side whose nearest multiple falls below the bound is rounded up: 505/14 = 36.07 -> 36*14
        // = 504 < 505 -> ceil -> 37*14 = 518.
        assert_eq!(size_hw(505, 505, 505), (518, 518));
        assert!(network_input_size(ImageSize::new(0, 10), 518).is_err());
        // Bounds: above the limit (the CLI once aborted on 140 000 px and panicked on 2^64 − 2),
        // and an aspect ratio that makes the input huge; the options also refuse what is not a
        // multiple of 14.
        for bad in [0, MAX_INPUT_SIZE_PX + 14, 140_000, usize::MAX - 1] {
            let e = network_input_size(ImageSize::new(640, 480), bad).unwrap_err();
            assert!(
                e.to_string().contains(&format!("bound {bad}"))
                    || e.to_string().contains(&format!("size {bad} px")),
                "{e}"
            );
        }
        assert_eq!(
            size_hw(480, 640, MAX_INPUT_SIZE_PX),
            (4200, 5600) // 5600 = 400 × 14
        );
        let e = network_input_size(ImageSize::new(16384, 2), 518).unwrap_err();
        assert!(e.to_string().contains("aspect ratio"), "{e}");
        // 4:1 is the limit: 2072×518 at 518 passes, a 3000×2 image at 112 px (112×168 000) not
        assert_eq!(size_hw(518, 2072, 518), (518, 2072));
        let e = network_input_size(ImageSize::new(3000, 2), 112)
            .unwrap_err()
            .to_string();
        assert!(e.contains("168000x112") && e.contains("4 times"), "{e}");
        assert!(network_input_size(ImageSize::new(2100, 518), 518).is_err());
        for (ok, size) in [
            (true, 14),
            (true, 518),
            (true, MAX_INPUT_SIZE_PX),
            (false, 0),
        ] {
            assert_eq!(check_input_size(size).is_ok(), ok, "{size}");
        }
        for bad in [517, MAX_INPUT_SIZE_PX + 14] {
            let e = check_input_size(bad).unwrap_err().to_string();
            assert!(
                e.contains("multiple of 14") && e.contains("at most 4200"),
                "{e}"
            );
        }
    }

    #[test]
    fn cubic_weights_hand_computed() {
        // Keys a = -0.75 at x = 0: (0, 1, 0, 0); at x = 0.5: (-0.09375, 0.59375, 0.59375, -0.09375).
        assert_eq!(opencv_cubic_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
        let w = opencv_cubic_weights(0.5);
        for (a, b) in w.iter().zip([-0.09375f32, 0.59375, 0.59375, -0.09375]) {
            assert!((a - b).abs() < 1e-7, "{w:?}");
        }
    }

    #[test]
    fn cubic_resize_tiny_case() {
        // 1x2 -> 1x4 (cv2.resize(np.array([[0., 1.]]), (4, 1), interpolation=cv2.INTER_CUBIC)):
        // scale 0.5, fx = -0.25, 0.25, 0.75, 1.25; w(0.75) = (-0.03515625, 0.26171875, 0.87890625,
        // -0.10546875), w(0.25) its reverse; replicated borders: taps (0,0,0,1), (0,0,1,1), (0,0,1,1),
        // (0,1,1,1).
        // Bytes 0 and 255 are 0.0 and 1.0; the output is normalised per channel.
        let src: Vec<u8> = [0u8, 255].iter().flat_map(|&v| [v, v, v]).collect();
        let mut out = vec![0.0f32; 3 * 4];
        resize_cubic_opencv_normalise(&src, ImageSize::new(2, 1), ImageSize::new(4, 1), &mut out);
        let expect = [-0.10546875, 0.2265625, 0.7734375, 1.10546875];
        for c in 0..3 {
            for (x, e) in expect.iter().enumerate() {
                let want = ((e - IMAGENET_MEAN[c]) / IMAGENET_STD[c]) as f32;
                assert!((out[c * 4 + x] - want).abs() < 1e-6, "{out:?}");
            }
        }
        // Constant images stay constant (weights sum to one).
        let mut out = vec![0.0f32; 3 * 9 * 11];
        resize_cubic_opencv_normalise(
            &[64u8; 5 * 7 * 3],
            ImageSize::new(7, 5),
            ImageSize::new(11, 9),
            &mut out,
        );
        for (c, plane) in out.chunks(9 * 11).enumerate() {
            let want = ((64.0 / 255.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c]) as f32;
            assert!(plane.iter().all(|v| (v - want).abs() < 1e-6), "{plane:?}");
        }
    }

    #[test]
    fn bilinear_align_corners_hand_computed() {
        use ndarray::array;
        // F.interpolate(torch.tensor([[[[0., 1.], [2., 3.]]]]), (3, 3), mode="bilinear", align_corners=True)
        let a = array![[0.0f32, 1.0], [2.0, 3.0]];
        let b = resize_bilinear_align_corners(&a.view(), 3, 3);
        assert_eq!(b, array![[0.0, 0.5, 1.0], [1.0, 1.5, 2.0], [2.0, 2.5, 3.0]]);
        // Downsizing 1x5 -> 1x3 picks columns 0, 2, 4.
        let a = array![[0.0f32, 1.0, 2.0, 3.0, 4.0]];
        let b = resize_bilinear_align_corners(&a.view(), 1, 3);
        assert_eq!(b, array![[0.0, 2.0, 4.0]]);
        // Identity.
        let b = resize_bilinear_align_corners(&a.view(), 1, 5);
        assert_eq!(b, a);
        // A non-contiguous view: resizing the transpose is the transpose of the resized map
        // (separable weights; up to the order of the two sums).
        let m = ndarray::Array2::from_shape_fn((4, 3), |(y, x)| ((y * 3 + x) as f32 * 0.7).sin());
        let t = m.t();
        assert!(t.as_slice().is_none());
        let want = resize_bilinear_align_corners(&m.view(), 6, 5).reversed_axes();
        let got = resize_bilinear_align_corners(&t, 5, 6);
        assert!(
            got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-6),
            "{got} vs {want}"
        );
    }
}
