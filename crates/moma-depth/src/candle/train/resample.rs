//! Bilinear `align_corners=True` resampling of `(N, h, w)` planes as a two-tap kernel (CPU f32 and
//! f64), with its adjoint: the interpolation is linear, so the input gradient is the transposed
//! map (each output's two-by-two taps scatter-added back). Replaces two dense interpolation
//! matrix products (`Rh · X · Rwᵀ`), whose cost grows with `h·w·(oh + ow)` instead of `oh·ow`.

use candle_core::{CpuStorage, CustomOp1, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::elem::Elem;

/// Taps `(i0, i1, w0, w1)` of one output index along one axis.
type Taps = Vec<(usize, usize, f64, f64)>;

/// The map `(N, h, w) → (N, oh, ow)` (forward) or its adjoint `(N, oh, ow) → (N, h, w)`.
struct Bilinear {
    rows: Taps,
    cols: Taps,
    /// `(h, w)`.
    input: (usize, usize),
    adjoint: bool,
}

/// The taps of `in_len → out_len`: computed in f64 when `f64_taps` (PyTorch computes an f64
/// tensor's interpolation weights in f64; the f32 taps cost a 5e-7 relative gradient error
/// against it), else the inference path's f32 taps ([`crate::preprocess::align_corners_taps`]),
/// so that f32 training equals f32 inference.
pub(crate) fn taps(in_len: usize, out_len: usize, f64_taps: bool) -> Taps {
    if !f64_taps {
        return crate::preprocess::align_corners_taps(in_len, out_len)
            .into_iter()
            .map(|(i0, i1, w0, w1)| (i0, i1, f64::from(w0), f64::from(w1)))
            .collect();
    }
    let scale = if out_len > 1 {
        (in_len as f64 - 1.0) / (out_len as f64 - 1.0)
    } else {
        0.0
    };
    (0..out_len)
        .map(|d| {
            let src = scale * d as f64;
            let i0 = (src as usize).min(in_len - 1);
            let i1 = (i0 + 1).min(in_len - 1);
            let l1 = src - i0 as f64;
            (i0, i1, 1.0 - l1, l1)
        })
        .collect()
}

impl Bilinear {
    fn output(&self) -> (usize, usize) {
        (self.rows.len(), self.cols.len())
    }

    /// One plane, forward: along the width into `tmp (h, ow)`, then along the height.
    fn forward_plane<T: Elem>(&self, x: &[T], y: &mut [T], tmp: &mut [T]) {
        let (h, w) = self.input;
        let ow = self.cols.len();
        for iy in 0..h {
            let src = &x[iy * w..(iy + 1) * w];
            for (o, &(i0, i1, w0, w1)) in tmp[iy * ow..(iy + 1) * ow].iter_mut().zip(&self.cols) {
                *o = T::of(w0) * src[i0] + T::of(w1) * src[i1];
            }
        }
        for (row, &(j0, j1, a0, a1)) in y.chunks_exact_mut(ow).zip(&self.rows) {
            let (r0, r1) = (&tmp[j0 * ow..(j0 + 1) * ow], &tmp[j1 * ow..(j1 + 1) * ow]);
            for ((o, &p), &q) in row.iter_mut().zip(r0).zip(r1) {
                *o = T::of(a0) * p + T::of(a1) * q;
            }
        }
    }

    /// One plane, adjoint: `g (oh, ow)` scattered back along the height into `tmp (h, ow)`,
    /// then along the width into `gx (h, w)`.
    fn adjoint_plane<T: Elem>(&self, g: &[T], gx: &mut [T], tmp: &mut [T]) {
        let (h, w) = self.input;
        let ow = self.cols.len();
        tmp.fill(T::default());
        for (row, &(j0, j1, a0, a1)) in g.chunks_exact(ow).zip(&self.rows) {
            for (o, &v) in tmp[j0 * ow..(j0 + 1) * ow].iter_mut().zip(row) {
                *o += T::of(a0) * v;
            }
            for (o, &v) in tmp[j1 * ow..(j1 + 1) * ow].iter_mut().zip(row) {
                *o += T::of(a1) * v;
            }
        }
        gx.fill(T::default());
        for iy in 0..h {
            let dst = &mut gx[iy * w..(iy + 1) * w];
            for (&v, &(i0, i1, w0, w1)) in tmp[iy * ow..(iy + 1) * ow].iter().zip(&self.cols) {
                dst[i0] += T::of(w0) * v;
                dst[i1] += T::of(w1) * v;
            }
        }
    }

    fn run<T: Elem>(&self, src: &[T], n: usize) -> Vec<T> {
        let (h, w) = self.input;
        let (oh, ow) = self.output();
        let (in_len, out_len) = if self.adjoint {
            (oh * ow, h * w)
        } else {
            (h * w, oh * ow)
        };
        let mut dst = vec![T::default(); n * out_len];
        dst.par_chunks_mut(out_len)
            .zip(src.par_chunks(in_len))
            .for_each_init(
                || vec![T::default(); h * ow],
                |tmp, (d, s)| {
                    if self.adjoint {
                        self.adjoint_plane(s, d, tmp);
                    } else {
                        self.forward_plane(s, d, tmp);
                    }
                },
            );
        dst
    }
}

impl CustomOp1 for Bilinear {
    fn name(&self) -> &'static str {
        "bilinear-align-corners"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, a, b) = layout.shape().dims3()?;
        let (h, w) = self.input;
        let (oh, ow) = self.output();
        let ((ea, eb), out) = if self.adjoint {
            ((oh, ow), (h, w))
        } else {
            ((h, w), (oh, ow))
        };
        if (a, b) != (ea, eb) {
            candle_core::bail!(
                "bilinear resampling: input {:?}, expected (N, {ea}, {eb})",
                layout.dims()
            );
        }
        let Some((o0, o1)) = layout.contiguous_offsets() else {
            candle_core::bail!("bilinear resampling: input must be contiguous");
        };
        let dst = match storage {
            CpuStorage::F32(v) => CpuStorage::F32(self.run(&v[o0..o1], n)),
            CpuStorage::F64(v) => CpuStorage::F64(self.run(&v[o0..o1], n)),
            _ => candle_core::bail!("bilinear resampling: f32 or f64 only"),
        };
        Ok((dst, Shape::from_dims(&[n, out.0, out.1])))
    }
}

/// Whether [`upsample`] has a kernel for `t`.
pub(crate) fn supported(t: &Tensor) -> bool {
    super::cpu_kernels(t)
}

/// Bilinear `align_corners=True` resampling of `(B, C, h, w)` to `(B, C, oh, ow)` (CPU f32/f64),
/// differentiable in `x` through the adjoint kernel.
///
/// # Errors
/// Shape errors, an unsupported device or dtype (see [`supported`]).
pub(crate) fn upsample(x: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    if h == 0 || w == 0 {
        candle_core::bail!("bilinear resampling of an empty {h}x{w} map");
    }
    let f64_taps = x.dtype() == DType::F64;
    let op = |adjoint: bool| Bilinear {
        rows: taps(h, oh, f64_taps),
        cols: taps(w, ow, f64_taps),
        input: (h, w),
        adjoint,
    };
    let (fwd, adj) = (op(false), op(true));
    let y = super::frozen::frozen(
        &x.reshape((b * c, h, w))?,
        move |x| x.apply_op1_no_bwd(&fwd),
        move |g| g.contiguous()?.apply_op1_no_bwd(&adj),
    )?;
    y.reshape((b, c, oh, ow))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(shape: &[usize], seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..shape.iter().product::<usize>())
            .map(|_| rng.random_range(-1.0..1.0))
            .collect()
    }

    /// Forward against the dense interpolation matrices `Rh · X · Rwᵀ` (independent: built
    /// entry by entry from the same taps), f32, up- and down-sampling.
    #[test]
    fn forward_matches_dense_interpolation_matrices() {
        for (h, w, oh, ow) in [(3, 4, 7, 9), (5, 6, 5, 6), (6, 7, 3, 4)] {
            let x = random(&[2, h, w], 1);
            let t = Tensor::from_vec(x.clone(), (1, 2, h, w), &Device::Cpu)
                .unwrap()
                .to_dtype(DType::F32)
                .unwrap();
            let got: Vec<f32> = upsample(&t, oh, ow)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let dense = |i: usize, o: usize| {
                let mut m = vec![0.0f64; o * i];
                for (d, (i0, i1, w0, w1)) in crate::preprocess::align_corners_taps(i, o)
                    .into_iter()
                    .enumerate()
                {
                    m[d * i + i0] += f64::from(w0);
                    m[d * i + i1] += f64::from(w1);
                }
                m
            };
            let (rh, rw) = (dense(h, oh), dense(w, ow));
            for p in 0..2 {
                for oy in 0..oh {
                    for ox in 0..ow {
                        let mut want = 0.0;
                        for iy in 0..h {
                            for ix in 0..w {
                                want +=
                                    rh[oy * h + iy] * x[p * h * w + iy * w + ix] * rw[ox * w + ix];
                            }
                        }
                        let g = f64::from(got[p * oh * ow + oy * ow + ox]);
                        assert!(
                            (g - want).abs() < 1e-6,
                            "{h}x{w}->{oh}x{ow} [{p},{oy},{ox}]: {g} vs {want}"
                        );
                    }
                }
            }
        }
    }

    /// The input gradient of `Σ upsample(x) ⊙ r` against central finite differences in f64
    /// (every entry), up- and down-sampling.
    #[test]
    fn gradient_matches_central_finite_differences_in_f64() {
        for (h, w, oh, ow) in [(3, 4, 7, 9), (6, 7, 3, 4)] {
            let shape = [1, 2, h, w];
            let x0 = random(&shape, 2);
            let r =
                Tensor::from_vec(random(&[1, 2, oh, ow], 3), (1, 2, oh, ow), &Device::Cpu).unwrap();
            crate::candle::train::testing::check_input_gradient(
                &format!("upsample {h}x{w}->{oh}x{ow}"),
                |x| upsample(x, oh, ow).unwrap(),
                &x0,
                &shape,
                &r,
                crate::candle::train::testing::FdCheck::EVERY_ENTRY,
            );
        }
    }
}
