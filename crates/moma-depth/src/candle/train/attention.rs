//! Memory-light multi-head attention for training: the forward keeps no `T × T` attention
//! probabilities (B·H·T² values per block: 45 MB per ViT-S block at 518², kept for the backward
//! together with the scores, shifted scores and exponentials a composed softmax makes), and the
//! backward recomputes them from q and k (as FlashAttention does). The graph keeps only the
//! `(B, T, 3C)` qkv projection and the `(B, T, C)` output.
//!
//! CPU f32 runs the inference kernel (blocked, the scores of a block of query rows in cache); CPU
//! f64 (gradient checks) a plain loop; other devices use composed candle operations.

use candle_core::{CpuStorage, CustomOp1, D, Layout, Result, Shape, Tensor};

use super::elem::Elem;

/// `softmax(scale · q kᵀ) v` per head on `qkv (B, T, 3C)` (PyTorch layout: `reshape(B, T, 3,
/// heads, C / heads)`) → `(B, T, C)`, differentiable in `qkv`.
///
/// # Errors
/// Shape errors, devices or dtypes without a kernel (callers use the composed path there).
pub(crate) fn attention(qkv: &Tensor, num_heads: usize, scale: f64) -> Result<Tensor> {
    qkv.contiguous()?
        .apply_op1(RecomputedAttention { num_heads, scale })
}

/// Whether [`attention`] has a kernel for `t`'s device and dtype.
pub(crate) fn supported(t: &Tensor) -> bool {
    super::cpu_kernels(t)
}

struct RecomputedAttention {
    num_heads: usize,
    scale: f64,
}

impl RecomputedAttention {
    fn dims(&self, layout: &Layout) -> Result<(usize, usize, usize, usize)> {
        let (b, t, c3) = layout.shape().dims3()?;
        let h = self.num_heads;
        if !c3.is_multiple_of(3) || h == 0 || !(c3 / 3).is_multiple_of(h) {
            candle_core::bail!("attention: qkv {:?}, {h} heads", layout.dims());
        }
        Ok((b, t, c3 / 3, (c3 / 3) / h))
    }
}

/// Plain attention on one `(t, 3c)` slice (f64; small inputs in gradient checks).
fn attention_f64(qkv: &[f64], t: usize, c: usize, heads: usize, scale: f64, out: &mut [f64]) {
    let hd = c / heads;
    let c3 = 3 * c;
    let mut s = vec![0.0f64; t];
    for h in 0..heads {
        for i in 0..t {
            let q = &qkv[i * c3 + h * hd..i * c3 + (h + 1) * hd];
            let mut max = f64::NEG_INFINITY;
            for (j, sj) in s.iter_mut().enumerate() {
                let k = &qkv[j * c3 + c + h * hd..j * c3 + c + (h + 1) * hd];
                *sj = scale * q.iter().zip(k).map(|(a, b)| a * b).sum::<f64>();
                max = max.max(*sj);
            }
            let mut sum = 0.0;
            for sj in &mut s {
                *sj = (*sj - max).exp();
                sum += *sj;
            }
            let o = &mut out[i * c + h * hd..i * c + (h + 1) * hd];
            o.fill(0.0);
            for (j, sj) in s.iter().enumerate() {
                let v = &qkv[j * c3 + 2 * c + h * hd..j * c3 + 2 * c + (h + 1) * hd];
                for (od, vd) in o.iter_mut().zip(v) {
                    *od += sj / sum * vd;
                }
            }
        }
    }
}

impl CustomOp1 for RecomputedAttention {
    fn name(&self) -> &'static str {
        "recomputed-attention"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, t, c, _) = self.dims(layout)?;
        let Some((o0, o1)) = layout.contiguous_offsets() else {
            candle_core::bail!("attention: qkv must be contiguous");
        };
        let per = t * 3 * c;
        let shape = Shape::from_dims(&[b, t, c]);
        match storage {
            CpuStorage::F32(v) => {
                let v = &v[o0..o1];
                let mut out = Vec::with_capacity(b * t * c);
                for k in 0..b {
                    out.extend(crate::candle::ops::attention_cpu_f32(
                        &v[k * per..(k + 1) * per],
                        t,
                        self.num_heads,
                        self.scale as f32,
                    )?);
                }
                Ok((CpuStorage::F32(out), shape))
            }
            CpuStorage::F64(v) => {
                let v = &v[o0..o1];
                let mut out = vec![0.0f64; b * t * c];
                for k in 0..b {
                    attention_f64(
                        &v[k * per..(k + 1) * per],
                        t,
                        c,
                        self.num_heads,
                        self.scale,
                        &mut out[k * t * c..(k + 1) * t * c],
                    );
                }
                Ok((CpuStorage::F64(out), shape))
            }
            _ => candle_core::bail!("attention: f32 or f64 only"),
        }
    }

    /// With `P = softmax(s·q kᵀ)` recomputed and `dO` the output gradient: `dV = Pᵀ dO`,
    /// `dP = dO vᵀ`, `dS = P ⊙ (dP − rowsum(dO ⊙ O))`, `dQ = s·dS k`, `dK = s·dSᵀ q`.
    /// CPU f32/f64: [`AttentionBackward`], blocks of query rows in cache (no `T × T` tensor);
    /// other devices: composed candle operations.
    fn bwd(&self, arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        if supported(arg) && grad_res.dtype() == arg.dtype() && grad_res.device().is_cpu() {
            let op = AttentionBackward {
                num_heads: self.num_heads,
                scale: self.scale,
            };
            let d = arg.detach().contiguous()?.apply_op3_no_bwd(
                &res.detach().contiguous()?,
                &grad_res.contiguous()?,
                &op,
            )?;
            return Ok(Some(d));
        }
        composed_backward(
            &arg.detach(),
            &res.detach(),
            grad_res,
            self.num_heads,
            self.scale,
        )
        .map(Some)
    }
}

/// q, k, v of `qkv (B, T, 3C)` as contiguous `(B, H, T, C / H)` tensors.
fn split_heads(qkv: &Tensor, h: usize) -> Result<(Tensor, Tensor, Tensor)> {
    let (b, t, c3) = qkv.dims3()?;
    let qkv = qkv
        .reshape((b, t, 3, h, c3 / 3 / h))?
        .permute((2, 0, 3, 1, 4))?;
    Ok((
        qkv.get(0)?.contiguous()?,
        qkv.get(1)?.contiguous()?,
        qkv.get(2)?.contiguous()?,
    ))
}

/// The attention forward from candle operations (any device), outside the graph: its `(B, H, T,
/// T)` scores and probabilities are freed on return.
fn composed_forward(qkv: &Tensor, h: usize, scale: f64) -> Result<Tensor> {
    let (b, t, c3) = qkv.dims3()?;
    let (q, k, v) = split_heads(qkv, h)?;
    let p = candle_nn::ops::softmax_last_dim(&(q.matmul(&k.t()?)? * scale)?)?;
    p.matmul(&v)?.transpose(1, 2)?.reshape((b, t, c3 / 3))
}

/// The attention backward from candle operations (any device), `P` recomputed: see
/// [`RecomputedAttention`]'s `bwd`. `o` is the forward's output, `go` its gradient.
fn composed_backward(
    qkv: &Tensor,
    o: &Tensor,
    go: &Tensor,
    h: usize,
    scale: f64,
) -> Result<Tensor> {
    let (b, t, c3) = qkv.dims3()?;
    let hd = c3 / 3 / h;
    let (q, k, v) = split_heads(qkv, h)?;
    let heads =
        |x: &Tensor| -> Result<Tensor> { x.reshape((b, t, h, hd))?.transpose(1, 2)?.contiguous() };
    let go = heads(go)?;
    let o = heads(o)?;
    let p = candle_nn::ops::softmax_last_dim(&(q.matmul(&k.t()?)? * scale)?)?;
    let dv = p.t()?.matmul(&go)?;
    let dp = go.matmul(&v.t()?)?;
    let delta = (&go * &o)?.sum_keepdim(D::Minus1)?;
    let ds = (p * dp.broadcast_sub(&delta)?)?;
    let dq = (ds.matmul(&k)? * scale)?;
    let dk = (ds.t()?.matmul(&q)? * scale)?;
    let d = Tensor::stack(&[dq, dk, dv], 0)?; // (3, B, H, T, hd)
    d.permute((1, 3, 0, 2, 4))?.reshape((b, t, c3))
}

/// [`attention`] on any device and dtype from candle operations: the same memory-light graph
/// (the forward's probabilities are not kept; the backward recomputes them), what a GPU runs.
///
/// # Errors
/// Shape errors.
pub(crate) fn attention_portable(qkv: &Tensor, num_heads: usize, scale: f64) -> Result<Tensor> {
    let o = composed_forward(&qkv.detach(), num_heads, scale)?;
    super::frozen::attach(qkv, o, move |qkv, o, go| {
        composed_backward(qkv, o, go, num_heads, scale)
    })
}

/// Query rows per block of [`AttentionBackward`] (two `rows × T` scratch blocks per task).
const BWD_ROWS: usize = 64;

/// The attention backward on CPU: `(qkv (B, T, 3C), O (B, T, C), dO (B, T, C))` → `dqkv (B, T,
/// 3C)`. One task per (image, head), in parallel; within a task, blocks of query rows in order:
/// scores `S = q_blk kᵀ`, `P = softmax(s·S)`, `dV += Pᵀ dO_blk`, `dP = dO_blk vᵀ`,
/// `dS = P ⊙ (dP − δ)` with `δᵢ = dOᵢ·Oᵢ`, `dQ_blk = s·dS k`, `dK += s·dSᵀ q_blk` (gemm).
struct AttentionBackward {
    num_heads: usize,
    scale: f64,
}

/// Element types of [`AttentionBackward`]: the kernels' [`Elem`] plus the forward's softmax.
trait BwdElem: Elem {
    /// `softmax(scale · row)` in place on the length-`n` rows of `s`.
    fn softmax_rows(s: &mut [Self], n: usize, scale: f64);
}

impl BwdElem for f32 {
    fn softmax_rows(s: &mut [Self], n: usize, scale: f64) {
        // The exponential of the forward kernel (`exp_rows`), so P is the forward's.
        crate::candle::ops::softmax_rows_in_place(s, n, scale as f32);
    }
}

impl BwdElem for f64 {
    fn softmax_rows(s: &mut [Self], n: usize, scale: f64) {
        for row in s.chunks_exact_mut(n) {
            let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let mut sum = 0.0;
            for v in row.iter_mut() {
                *v = ((*v - max) * scale).exp();
                sum += *v;
            }
            for v in row.iter_mut() {
                *v /= sum;
            }
        }
    }
}

/// A raw pointer shared by tasks that write disjoint elements.
#[derive(Clone, Copy)]
struct Shared<T>(*mut T);
impl<T> Shared<T> {
    /// The pointer (a method, so that closures capture the whole `Sync` wrapper).
    fn get(self) -> *mut T {
        self.0
    }
}
// SAFETY: only used for disjoint writes from rayon tasks.
unsafe impl<T> Send for Shared<T> {}
// SAFETY: as above.
unsafe impl<T> Sync for Shared<T> {}

/// `dst = [dst +] beta · lhs · rhs` with strided operands `(ptr, row stride, column stride)`,
/// single-threaded (the caller runs tasks in parallel).
///
/// # Safety
/// Every addressed element must be valid; `dst` must not alias `lhs` or `rhs`.
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_into<T: BwdElem>(
    (m, n, k): (usize, usize, usize),
    dst: (*mut T, isize),
    accumulate: bool,
    lhs: (*const T, isize, isize),
    rhs: (*const T, isize, isize),
    beta: T,
) {
    // SAFETY: forwarded to the caller.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.0,
            1,
            dst.1,
            accumulate,
            lhs.0,
            lhs.2,
            lhs.1,
            rhs.0,
            rhs.2,
            rhs.1,
            T::of(1.0),
            beta,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

impl AttentionBackward {
    /// `dqkv` of one image and head `h` (columns `h·hd..` of the q, k and v parts of `d`).
    ///
    /// # Safety
    /// `d` points at a zeroed `(t, 3c)` buffer whose head-`h` columns no other task touches.
    #[allow(clippy::too_many_arguments)]
    unsafe fn head<T: BwdElem>(
        &self,
        qkv: &[T],
        o: &[T],
        go: &[T],
        d: *mut T,
        (t, c, h, hd): (usize, usize, usize, usize),
        s: &mut [T],
        dp: &mut [T],
    ) {
        let c3 = 3 * c;
        let (rs3, rs1) = (c3 as isize, c as isize);
        let scale = T::of(self.scale);
        let col = h * hd;
        let base = qkv.as_ptr();
        let mut r0 = 0;
        while r0 < t {
            let rows = BWD_ROWS.min(t - r0);
            let s = &mut s[..rows * t];
            let dp = &mut dp[..rows * t];
            let tt = t as isize;
            // SAFETY: every offset stays inside qkv/o/go (t × 3c, t × c) and the scratch blocks;
            // d's writes are this head's columns (the caller's contract).
            unsafe {
                let q_blk = (base.add(r0 * c3 + col), rs3, 1);
                let k = base.add(c + col);
                let v = base.add(2 * c + col);
                let go_blk = (go.as_ptr().add(r0 * c + col), rs1, 1);
                // S = q_blk · kᵀ
                gemm_into(
                    (rows, t, hd),
                    (s.as_mut_ptr(), tt),
                    false,
                    q_blk,
                    (k, 1, rs3),
                    T::of(1.0),
                );
                T::softmax_rows(s, t, self.scale);
                // dV += Pᵀ · dO_blk
                gemm_into(
                    (t, hd, rows),
                    (d.add(2 * c + col), rs3),
                    true,
                    (s.as_ptr(), 1, tt),
                    go_blk,
                    T::of(1.0),
                );
                // dP = dO_blk · vᵀ
                gemm_into(
                    (rows, t, hd),
                    (dp.as_mut_ptr(), tt),
                    false,
                    go_blk,
                    (v, 1, rs3),
                    T::of(1.0),
                );
                // dS = P ⊙ (dP − δ), δᵢ = dOᵢ · Oᵢ
                for (i, (ds, p)) in dp.chunks_exact_mut(t).zip(s.chunks_exact(t)).enumerate() {
                    let r = (r0 + i) * c + col;
                    let mut delta = T::ZERO;
                    for (a, b) in go[r..r + hd].iter().zip(&o[r..r + hd]) {
                        delta += *a * *b;
                    }
                    for (x, &pv) in ds.iter_mut().zip(p) {
                        *x = pv * (*x - delta);
                    }
                }
                // dQ_blk = s · dS · k
                gemm_into(
                    (rows, hd, t),
                    (d.add(r0 * c3 + col), rs3),
                    false,
                    (dp.as_ptr(), tt, 1),
                    (k, rs3, 1),
                    scale,
                );
                // dK += s · dSᵀ · q_blk
                gemm_into(
                    (t, hd, rows),
                    (d.add(c + col), rs3),
                    true,
                    (dp.as_ptr(), 1, tt),
                    q_blk,
                    scale,
                );
            }
            r0 += rows;
        }
    }

    fn run<T: BwdElem>(&self, qkv: &[T], o: &[T], go: &[T], dims: [usize; 3]) -> Vec<T> {
        use rayon::prelude::*;
        let [b, t, c] = dims;
        let h = self.num_heads;
        let hd = c / h;
        let mut d = vec![T::ZERO; b * t * 3 * c];
        let dst = Shared(d.as_mut_ptr());
        let rows = BWD_ROWS.min(t);
        (0..b * h).into_par_iter().for_each_init(
            || (vec![T::ZERO; rows * t], vec![T::ZERO; rows * t]),
            |(s, dp), task| {
                let (bi, hi) = (task / h, task % h);
                let (q0, o0) = (bi * t * 3 * c, bi * t * c);
                // SAFETY: image bi's slice of d, head hi's columns: disjoint across tasks.
                unsafe {
                    self.head(
                        &qkv[q0..q0 + t * 3 * c],
                        &o[o0..o0 + t * c],
                        &go[o0..o0 + t * c],
                        dst.get().add(q0),
                        (t, c, hi, hd),
                        s,
                        dp,
                    );
                }
            },
        );
        d
    }
}

impl candle_core::CustomOp3 for AttentionBackward {
    fn name(&self) -> &'static str {
        "recomputed-attention-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, t, c3) = l1.shape().dims3()?;
        let c = c3 / 3;
        let h = self.num_heads;
        if !c3.is_multiple_of(3) || h == 0 || !c.is_multiple_of(h) {
            candle_core::bail!("attention backward: qkv {:?}, {h} heads", l1.dims());
        }
        if l2.dims() != [b, t, c] || l3.dims() != [b, t, c] {
            candle_core::bail!(
                "attention backward: qkv {:?}, output {:?}, gradient {:?}",
                l1.dims(),
                l2.dims(),
                l3.dims()
            );
        }
        let (Some(r1), Some(r2), Some(r3)) = (
            l1.contiguous_offsets(),
            l2.contiguous_offsets(),
            l3.contiguous_offsets(),
        ) else {
            candle_core::bail!("attention backward: operands must be contiguous");
        };
        let dims = [b, t, c];
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(a), CpuStorage::F32(o), CpuStorage::F32(g)) => {
                CpuStorage::F32(self.run(&a[r1.0..r1.1], &o[r2.0..r2.1], &g[r3.0..r3.1], dims))
            }
            (CpuStorage::F64(a), CpuStorage::F64(o), CpuStorage::F64(g)) => {
                CpuStorage::F64(self.run(&a[r1.0..r1.1], &o[r2.0..r2.1], &g[r3.0..r3.1], dims))
            }
            _ => candle_core::bail!("attention backward: f32 or f64 operands of one dtype"),
        };
        Ok((out, Shape::from_dims(&[b, t, c3])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(n: usize, seed: u64, range: f64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.random_range(-range..range)).collect()
    }

    /// `L = Σ attention(qkv) ⊙ r` for 2 images, 2 heads of 3 channels and 150 tokens (three
    /// blocks of query rows, the last partial).
    const DIMS: (usize, usize, usize, usize) = (2, 150, 2, 3);

    /// Every 37th entry of qkv (over 100 of them), relative error below 1e-5.
    const SAMPLED: crate::candle::train::testing::FdCheck =
        crate::candle::train::testing::FdCheck {
            stride: 37,
            floor: 1e-6,
            tol: 1e-5,
        };

    fn setup() -> (Vec<f64>, Tensor, f64) {
        let (b, t, h, hd) = DIMS;
        let c = h * hd;
        let qkv = random(b * t * 3 * c, 11, 1.5);
        let r = Tensor::from_vec(random(b * t * c, 12, 1.0), (b, t, c), &Device::Cpu).unwrap();
        (qkv, r, 1.0 / (hd as f64).sqrt())
    }

    /// The fused backward's gradient against central finite differences in f64 (a sample of
    /// entries of q, k and v in both images).
    #[test]
    fn fused_backward_matches_central_finite_differences_in_f64() {
        let (b, t, h, hd) = DIMS;
        let c3 = 3 * h * hd;
        let (x0, r, scale) = setup();
        let shape = [b, t, c3];
        let g = crate::candle::train::testing::check_input_gradient(
            "fused attention qkv",
            |x| attention(x, h, scale).unwrap(),
            &x0,
            &shape,
            &r,
            SAMPLED,
        );
        assert!(x0.len() / 37 > 100);
        assert!(g.iter().any(|v| v.abs() > 1e-3));
    }

    /// The portable attention (candle operations, what a GPU runs): forward equal to the
    /// kernel's, gradient against central finite differences in f64.
    #[test]
    fn portable_attention_matches_the_kernel_and_central_finite_differences_in_f64() {
        let (b, t, h, hd) = DIMS;
        let c3 = 3 * h * hd;
        let (x0, r, scale) = setup();
        let x = Tensor::from_slice(&x0, (b, t, c3), &Device::Cpu).unwrap();
        let o_kernel = attention(&x, h, scale).unwrap();
        let o_portable = attention_portable(&x, h, scale).unwrap();
        let diff = crate::candle::train::testing::max_abs_diff(&o_kernel, &o_portable);
        assert!(diff < 1e-12, "forward differs by {diff}");
        let g = crate::candle::train::testing::check_input_gradient(
            "portable attention qkv",
            |x| attention_portable(x, h, scale).unwrap(),
            &x0,
            &[b, t, c3],
            &r,
            SAMPLED,
        );
        assert!(g.iter().any(|v| v.abs() > 1e-3));
    }

    /// The fused f32 backward equals the portable backward (candle operations on the full
    /// `T × T` probabilities: what a GPU runs) of the same op.
    #[test]
    fn fused_f32_backward_equals_the_portable_backward() {
        let (b, t, h, hd) = DIMS;
        let c3 = 3 * h * hd;
        let (x0, r, scale) = setup();
        let x = Tensor::from_vec(x0, (b, t, c3), &Device::Cpu)
            .unwrap()
            .to_dtype(DType::F32)
            .unwrap();
        let r = r.to_dtype(DType::F32).unwrap();
        let op = RecomputedAttention {
            num_heads: h,
            scale,
        };
        let o = x.apply_op1_no_bwd(&op).unwrap();
        let fused = op.bwd(&x, &o, &r).unwrap().unwrap();
        let want = composed_backward(&x, &o, &r, h, scale).unwrap();
        let a: Vec<f32> = fused.flatten_all().unwrap().to_vec1().unwrap();
        let w: Vec<f32> = want.flatten_all().unwrap().to_vec1().unwrap();
        let scale_w = w.iter().fold(0f32, |m, v| m.max(v.abs()));
        let err = a
            .iter()
            .zip(&w)
            .fold(0f32, |m, (x, y)| m.max((x - y).abs()))
            / scale_w;
        assert!(err < 1e-5, "relative difference {err:.2e}");
    }
}
