//! The fine-tuning data pipeline: frames of moma sets at network resolution, a seeded split by
//! frame, and the random crops, flips and colour jitter of each training step.
//!
//! Every random draw comes from a generator the caller seeds (see
//! [`moma_depth::candle::train::derive_seed`]), so a run resumed at step k draws exactly what the
//! uninterrupted run drew from step k on.

use std::path::PathBuf;

use moma_core::ImageSize;
use moma_depth::candle::train::Sample;
use moma_depth::preprocess;
use moma_io::MomaSet;
use ndarray::{Array2, Array3, Axis, s};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::TrainError;

/// One frame at network resolution (before cropping and augmentation): the whole frame is the
/// validation sample as it is.
#[derive(Debug, Clone)]
pub struct Frame {
    /// `SET/frames/ID`, for messages.
    pub name: String,
    /// The pre-processed input `(3, H, W)` (ImageNet-normalised; H, W multiples of 14), the
    /// ground truth (metres, resized by nearest neighbour) and, with `mask_loss`, the mask.
    pub sample: Sample,
}

/// Nearest-neighbour resize (ground truth and masks must not be blended across edges).
pub fn resize_nearest<T: Copy>(src: &Array2<T>, h: usize, w: usize) -> Array2<T> {
    let (sh, sw) = src.dim();
    Array2::from_shape_fn((h, w), |(y, x)| {
        let sy = ((y as f64 + 0.5) * sh as f64 / h as f64).floor() as usize;
        let sx = ((x as f64 + 0.5) * sw as f64 / w as f64).floor() as usize;
        src[[sy.min(sh - 1), sx.min(sw - 1)]]
    })
}

/// Reads every frame of `sets` at the network resolution of `input_size` (as `moma predict`
/// pre-processes: the shorter side to `input_size`, aspect kept, both sides multiples of 14),
/// with the frames' masks when `mask_loss`.
///
/// # Errors
/// An unreadable set or file, an empty set, frames of mixed sizes (one camera per run), a
/// ground-truth map without any valid pixel; each names the file or frame.
pub fn load_frames(
    sets: &[PathBuf],
    input_size: usize,
    mask_loss: bool,
) -> Result<Vec<Frame>, TrainError> {
    let mut out = vec![];
    let mut size: Option<(ImageSize, String)> = None;
    for root in sets {
        let set = MomaSet::open(root)?;
        if set.frames.is_empty() {
            return Err(TrainError::Data(format!(
                "moma set {} has no frames",
                root.display()
            )));
        }
        for f in &set.frames {
            let name = format!("{}/frames/{}", root.display(), f.id);
            match &size {
                None => size = Some((f.size, name.clone())),
                Some((s, first)) if *s != f.size => {
                    return Err(TrainError::Data(format!(
                        "frames of mixed sizes: {name} is {}x{}, {first} is {}x{} (fine-tune on one camera's frames)",
                        f.size.width, f.size.height, s.width, s.height
                    )));
                }
                Some(_) => {}
            }
            let rgb = f.load_rgb()?;
            let depth = f.load_depth()?;
            if !depth.depth_m.iter().any(|&d| d.is_finite() && d > 0.0) {
                return Err(TrainError::Data(format!(
                    "{name}: the ground-truth depth {} has no valid pixel",
                    f.depth.display()
                )));
            }
            let input = preprocess::preprocess(&rgb, input_size)?;
            let (_, h, w) = input.dim();
            let gt_m = resize_nearest(&depth.depth_m, h, w);
            let mask = if mask_loss {
                let m = f.load_mask_or_full()?;
                Some(resize_nearest(m.data(), h, w))
            } else {
                None
            };
            out.push(Frame {
                name,
                sample: Sample { input, gt_m, mask },
            });
        }
    }
    Ok(out)
}

/// A seeded split by frame: `(training, validation)`. `val_frac` of the frames (rounded, at
/// least one when `val_frac > 0`) are held out, after a shuffle seeded by `seed`.
///
/// # Errors
/// `val_frac` outside `[0, 1)`; too few frames to leave one for training.
pub fn split(
    mut frames: Vec<Frame>,
    val_frac: f64,
    seed: u64,
) -> Result<(Vec<Frame>, Vec<Frame>), TrainError> {
    if !(0.0..1.0).contains(&val_frac) {
        return Err(TrainError::Invalid(format!(
            "val_frac {val_frac} must be in [0, 1)"
        )));
    }
    frames.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let n_val = if val_frac > 0.0 {
        ((frames.len() as f64 * val_frac).round() as usize).max(1)
    } else {
        0
    };
    if frames.len() <= n_val {
        return Err(TrainError::Data(format!(
            "{} frame(s) cannot be split into training and validation (val_frac {val_frac}); add frames or use a validation fraction of 0",
            frames.len()
        )));
    }
    let train = frames.split_off(n_val);
    Ok((train, frames))
}

/// A random `crop` (H, W) of the network-size frame (the whole frame when `None`; a crop larger
/// than the frame is cut to it), with a horizontal flip (p = 0.5) and brightness/contrast
/// jitter (±20 %, in RGB before the ImageNet normalisation, clamped to [0, 1]) when `augment`.
pub fn training_sample(
    f: &Frame,
    crop: Option<(usize, usize)>,
    augment: bool,
    rng: &mut ChaCha8Rng,
) -> Sample {
    let f = &f.sample;
    let (_, h, w) = f.input.dim();
    let (ch, cw) = crop.map_or((h, w), |(ch, cw)| (ch.min(h), cw.min(w)));
    let y0 = rng.random_range(0..=h - ch);
    let x0 = rng.random_range(0..=w - cw);
    let mut input = f.input.slice(s![.., y0..y0 + ch, x0..x0 + cw]).to_owned();
    let mut gt_m = f.gt_m.slice(s![y0..y0 + ch, x0..x0 + cw]).to_owned();
    let mut mask = f
        .mask
        .as_ref()
        .map(|m| m.slice(s![y0..y0 + ch, x0..x0 + cw]).to_owned());
    if augment {
        if rng.random_bool(0.5) {
            input.invert_axis(Axis(2));
            gt_m.invert_axis(Axis(1));
            if let Some(m) = &mut mask {
                m.invert_axis(Axis(1));
            }
        }
        let brightness: f64 = rng.random_range(0.8..1.2);
        let contrast: f64 = rng.random_range(0.8..1.2);
        jitter(&mut input, brightness, contrast);
    }
    Sample { input, gt_m, mask }
}

/// Brightness/contrast jitter of an ImageNet-normalised input: back to [0, 1] RGB, contrast about
/// the mean, brightness, clamp, re-normalise.
fn jitter(input: &mut Array3<f32>, brightness: f64, contrast: f64) {
    let mut raw = input.clone();
    for c in 0..3 {
        let (m, sd) = (preprocess::IMAGENET_MEAN[c], preprocess::IMAGENET_STD[c]);
        raw.index_axis_mut(Axis(0), c)
            .mapv_inplace(|v| (f64::from(v) * sd + m) as f32);
    }
    let mean = raw.mean().unwrap_or(0.5);
    for c in 0..3 {
        let (m, sd) = (preprocess::IMAGENET_MEAN[c], preprocess::IMAGENET_STD[c]);
        let src = raw.index_axis(Axis(0), c);
        let mut dst = input.index_axis_mut(Axis(0), c);
        ndarray::Zip::from(&mut dst).and(&src).for_each(|d, &v| {
            let j = ((f64::from(v) - f64::from(mean)) * contrast + f64::from(mean)) * brightness;
            *d = ((j.clamp(0.0, 1.0) - m) / sd) as f32;
        });
    }
}

/// The frame visited at draw `j` (frame order reshuffled every epoch with a seed derived from
/// `seed` and the epoch), cached in `order` between calls.
pub fn frame_at(
    j: u64,
    n_frames: usize,
    seed: u64,
    order: &mut (Option<u64>, Vec<usize>),
) -> usize {
    use moma_depth::candle::train::{derive_seed, seed_tag};
    let epoch = j / n_frames as u64;
    if order.0 != Some(epoch) {
        let mut perm: Vec<usize> = (0..n_frames).collect();
        perm.shuffle(&mut ChaCha8Rng::seed_from_u64(derive_seed(
            seed,
            seed_tag::ORDER,
            epoch,
        )));
        *order = (Some(epoch), perm);
    }
    order.1[(j % n_frames as u64) as usize]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(h: usize, w: usize) -> Frame {
        Frame {
            name: "f".into(),
            sample: Sample {
                input: Array3::from_shape_fn((3, h, w), |(c, y, x)| {
                    (c * 100 + y * 10 + x) as f32 * 1e-3
                }),
                gt_m: Array2::from_shape_fn((h, w), |(y, x)| 1.0 + (y * w + x) as f32),
                mask: Some(Array2::from_shape_fn((h, w), |(_, x)| x < 2)),
            },
        }
    }

    #[test]
    fn crops_keep_input_ground_truth_and_mask_aligned() {
        let f = frame(28, 42);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let s = training_sample(&f, Some((14, 28)), true, &mut rng);
            assert_eq!(s.input.dim(), (3, 14, 28));
            assert_eq!(s.gt_m.dim(), (14, 28));
            // The ground truth encodes its source pixel: the crop is a contiguous window,
            // possibly mirrored, and the mask travels with it.
            let g = |y: usize, x: usize| s.gt_m[[y, x]] as usize - 1;
            let (y0, x0) = (g(0, 0) / 42, g(0, 0) % 42);
            let flipped = g(0, 1) + 1 == g(0, 0);
            for y in 0..14 {
                for x in 0..28 {
                    let sx = if flipped { x0 - x } else { x0 + x };
                    assert_eq!(g(y, x), (y0 + y) * 42 + sx);
                    assert_eq!(s.mask.as_ref().unwrap()[[y, x]], sx < 2);
                }
            }
        }
        // Without augmentation the input is the crop's values exactly.
        let s = training_sample(&f, Some((14, 28)), false, &mut rng);
        let g0 = s.gt_m[[0, 0]] as usize - 1;
        let (y0, x0) = (g0 / 42, g0 % 42);
        assert_eq!(s.input[[2, 3, 4]], f.sample.input[[2, y0 + 3, x0 + 4]]);
    }

    #[test]
    fn jitter_is_identity_at_one_and_clamps() {
        let mut x = Array3::from_elem((3, 2, 2), 0.0f32);
        let before = x.clone();
        jitter(&mut x, 1.0, 1.0);
        for (a, b) in x.iter().zip(&before) {
            assert!((a - b).abs() < 1e-6);
        }
        // Brightness 1.2 on white saturates at 1.0 in RGB: (1 − mean) / std per channel.
        let c0 = ((1.0 - preprocess::IMAGENET_MEAN[0]) / preprocess::IMAGENET_STD[0]) as f32;
        let mut white = Array3::from_shape_fn((3, 1, 1), |(c, _, _)| {
            ((1.0 - preprocess::IMAGENET_MEAN[c]) / preprocess::IMAGENET_STD[c]) as f32
        });
        jitter(&mut white, 1.2, 1.0);
        assert!((white[[0, 0, 0]] - c0).abs() < 1e-5);
    }

    #[test]
    fn split_is_seeded_and_leaves_training_frames() {
        let frames: Vec<Frame> = (0..5)
            .map(|i| Frame {
                name: format!("f{i}"),
                ..frame(14, 14)
            })
            .collect();
        let (t1, v1) = split(frames.clone(), 0.2, 7).unwrap();
        let (t2, v2) = split(frames.clone(), 0.2, 7).unwrap();
        assert_eq!((t1.len(), v1.len()), (4, 1));
        let names = |f: &[Frame]| f.iter().map(|f| f.name.clone()).collect::<Vec<_>>();
        assert_eq!(names(&t1), names(&t2));
        assert_eq!(names(&v1), names(&v2));
        assert!(split(frames[..1].to_vec(), 0.2, 7).is_err());
        assert!(split(frames, 1.0, 7).is_err());
    }

    #[test]
    fn every_frame_once_per_epoch() {
        let mut order = (None, vec![]);
        let mut seen: Vec<usize> = (0..7).map(|j| frame_at(j, 7, 1, &mut order)).collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..7).collect::<Vec<_>>());
    }
}
