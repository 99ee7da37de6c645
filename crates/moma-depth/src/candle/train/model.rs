//! The Depth Anything V2 network built from differentiable candle operations only (docs/method.md §9):
//! LayerNorm from mean/variance, softmax with a detached maximum, exact-erf GELU, LayerScale as a
//! product, convolutions with candle's `conv2d` (which has a backward), and both resampling steps —
//! the bicubic position-embedding interpolation and the bilinear `align_corners` upsampling of the
//! DPT head — as products with interpolation matrices (linear maps, so exact and differentiable).
//! Batched: `(B, 3, H, W)` in, `(B, H, W)` out. The inference path keeps its fused kernels.

use std::collections::{BTreeMap, BTreeSet};

use candle_core::{D, DType, Device, Result, Tensor, Var};
use candle_nn::VarBuilder;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::adapter::Adapter;
use super::frozen::frozen;
use super::lora::{LoraConfig, LoraTarget};
use crate::Head;
use crate::candle::DepthAnythingConfig;
use crate::candle::dinov2::{POS_EMBED_INTERPOLATE_OFFSET, torch_cubic_coefficients};
use crate::preprocess::PATCH_SIZE;

/// Where the tensors of the training network come from: the base weights (a [`VarBuilder`] with
/// the official key names) and which of them are trained ([`Var`]s, collected by name).
pub struct ParamSource<'a> {
    vb: VarBuilder<'a>,
    trainable: Box<dyn Fn(&str) -> bool + 'a>,
    vars: BTreeMap<String, Var>,
}

impl<'a> ParamSource<'a> {
    /// Base weights `vb`; `trainable(name)` says which official keys become trained variables.
    pub fn new(vb: VarBuilder<'a>, trainable: impl Fn(&str) -> bool + 'a) -> Self {
        Self {
            vb,
            trainable: Box::new(trainable),
            vars: BTreeMap::new(),
        }
    }

    fn get<S: Into<candle_core::Shape>>(&mut self, shape: S, name: &str) -> Result<Tensor> {
        let t = self.vb.get(shape, name)?;
        let full = self.vb.prefix().is_empty().then(|| name.to_string());
        let full = full.unwrap_or_else(|| format!("{}.{name}", self.vb.prefix()));
        if (self.trainable)(&full) {
            let v = Var::from_tensor(&t.detach())?;
            let t = v.as_tensor().clone();
            self.vars.insert(full, v);
            Ok(t)
        } else {
            Ok(t.detach())
        }
    }

    fn pp(&mut self, s: &str) -> PrefixGuard<'_, 'a> {
        let old = self.vb.clone();
        self.vb = self.vb.pp(s);
        PrefixGuard { src: self, old }
    }
}

/// Restores the prefix of a [`ParamSource`] when dropped.
struct PrefixGuard<'s, 'a> {
    src: &'s mut ParamSource<'a>,
    old: VarBuilder<'a>,
}

impl<'a> std::ops::Deref for PrefixGuard<'_, 'a> {
    type Target = ParamSource<'a>;
    fn deref(&self) -> &Self::Target {
        self.src
    }
}

impl std::ops::DerefMut for PrefixGuard<'_, '_> {
    fn deref_mut(&mut self) -> &mut Self::Target {
        self.src
    }
}

impl Drop for PrefixGuard<'_, '_> {
    fn drop(&mut self) {
        self.src.vb = self.old.clone();
    }
}

/// One LoRA adapter on a slice of a linear layer's output rows:
/// `y[.., offset..offset+rows] += scale · (drop(x)·Aᵀ)·Bᵀ`.
#[derive(Debug, Clone)]
pub struct LoraPart {
    /// `(r, in)`.
    pub a: Var,
    /// `(rows, r)`.
    pub b: Var,
    /// First output row the adapter writes.
    pub offset: usize,
    /// `α / r`.
    pub scale: f64,
}

/// `nn.Linear` with optional LoRA adapters.
#[derive(Debug, Clone)]
struct TLinear {
    /// `(out, in)`.
    w: Tensor,
    b: Tensor,
    lora: Vec<LoraPart>,
}

impl TLinear {
    fn new(src: &mut ParamSource, in_dim: usize, out_dim: usize) -> Result<Self> {
        Ok(Self {
            w: src.get((out_dim, in_dim), "weight")?,
            b: src.get(out_dim, "bias")?,
            lora: vec![],
        })
    }

    fn forward(&self, x: &Tensor, dropout: &mut Dropout) -> Result<Tensor> {
        let out_dim = self.w.dim(0)?;
        let mut y = if !self.w.track_op() && !self.b.track_op() && x.rank() == 3 {
            // Frozen weight and bias: one gemm accumulating into the bias rows (the inference
            // path's `linear`), input-only backward.
            let (w_t, b, w2) = (self.w.t()?.contiguous()?, self.b.clone(), self.w.clone());
            frozen(
                x,
                move |x| {
                    let (n, t, k) = x.dims3()?;
                    let y = crate::candle::ops::linear(
                        &x.reshape((n * t, k))?,
                        &w_t,
                        &b,
                        None,
                        crate::candle::ops::Activation::None,
                    )?;
                    y.reshape((n, t, out_dim))
                },
                move |g| g.broadcast_matmul(&w2),
            )?
        } else if self.w.is_variable() {
            x.broadcast_matmul(&self.w.t()?)?.broadcast_add(&self.b)?
        } else {
            let (w1, w2) = (self.w.clone(), self.w.clone());
            frozen(
                x,
                move |x| x.broadcast_matmul(&w1.t()?),
                move |g| g.broadcast_matmul(&w2),
            )?
            .broadcast_add(&self.b)?
        };
        if !self.lora.is_empty() {
            let xd = dropout.apply(x)?;
            for p in &self.lora {
                let rows = p.b.dim(0)?;
                let d = xd
                    .broadcast_matmul(&p.a.as_tensor().t()?)?
                    .broadcast_matmul(&p.b.as_tensor().t()?)?
                    .affine(p.scale, 0.0)?;
                let d = d.pad_with_zeros(D::Minus1, p.offset, out_dim - p.offset - rows)?;
                y = (y + d)?;
            }
        }
        Ok(y)
    }
}

/// Inverted dropout on the LoRA input with a seeded generator (`p = 0`: identity).
#[derive(Debug)]
pub(crate) struct Dropout {
    p: f32,
    active: bool,
    rng: ChaCha8Rng,
}

impl Dropout {
    pub(crate) fn new(p: f32, seed: u64) -> Self {
        Self {
            p,
            active: false,
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    fn apply(&mut self, x: &Tensor) -> Result<Tensor> {
        if !self.active || self.p <= 0.0 {
            return Ok(x.clone());
        }
        let keep = 1.0 - self.p;
        let mask: Vec<f32> = (0..x.elem_count())
            .map(|_| {
                if self.rng.random::<f32>() < keep {
                    1.0 / keep
                } else {
                    0.0
                }
            })
            .collect();
        let mask = Tensor::from_vec(mask, x.shape(), x.device())?.to_dtype(x.dtype())?;
        x * mask
    }
}

/// Softmax over the last dimension; the maximum is detached (softmax is shift-invariant, so the
/// gradient is exact).
fn softmax_last(x: &Tensor) -> Result<Tensor> {
    let max = x.max_keepdim(D::Minus1)?.detach();
    let e = x.broadcast_sub(&max)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

#[derive(Debug, Clone)]
struct Ln {
    w: Tensor,
    b: Tensor,
    eps: f64,
}

impl Ln {
    fn new(src: &mut ParamSource, dim: usize, eps: f64) -> Result<Self> {
        Ok(Self {
            w: src.get(dim, "weight")?,
            b: src.get(dim, "bias")?,
            eps,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if super::norm::supported(x, &self.w, &self.b) {
            return super::norm::layer_norm(x, &self.w, &self.b, self.eps);
        }
        if !self.w.track_op() && !self.b.track_op() {
            return super::norm::layer_norm_portable(x, &self.w, &self.b, self.eps);
        }
        super::norm::layer_norm_composed(x, &self.w, &self.b, self.eps)
    }
}

#[derive(Debug, Clone)]
struct TBlock {
    norm1: Ln,
    qkv: TLinear,
    proj: TLinear,
    ls1: Tensor,
    norm2: Ln,
    fc1: TLinear,
    fc2: TLinear,
    ls2: Tensor,
    num_heads: usize,
    /// Attention that keeps no probabilities and recomputes them in the backward (a kernel on
    /// the CPU, candle operations elsewhere).
    recompute_attention: bool,
}

impl TBlock {
    fn new(src: &mut ParamSource, cfg: &DepthAnythingConfig) -> Result<Self> {
        let d = cfg.embed_dim;
        let eps = cfg.layer_norm_eps;
        let norm1 = Ln::new(&mut src.pp("norm1"), d, eps)?;
        let qkv = TLinear::new(&mut src.pp("attn.qkv"), d, 3 * d)?;
        let proj = TLinear::new(&mut src.pp("attn.proj"), d, d)?;
        let ls1 = src.get(d, "ls1.gamma")?;
        let norm2 = Ln::new(&mut src.pp("norm2"), d, eps)?;
        let fc1 = TLinear::new(&mut src.pp("mlp.fc1"), d, cfg.mlp_hidden_dim)?;
        let fc2 = TLinear::new(&mut src.pp("mlp.fc2"), cfg.mlp_hidden_dim, d)?;
        let ls2 = src.get(d, "ls2.gamma")?;
        Ok(Self {
            norm1,
            qkv,
            proj,
            ls1,
            norm2,
            fc1,
            fc2,
            ls2,
            num_heads: cfg.num_heads,
            recompute_attention: true,
        })
    }

    fn forward(&self, x: &Tensor, dropout: &mut Dropout) -> Result<Tensor> {
        let (b, t, d) = x.dims3()?;
        let h = self.num_heads;
        let hd = d / h;
        let qkv = self.qkv.forward(&self.norm1.forward(x)?, dropout)?;
        let scale = 1.0 / (hd as f64).sqrt();
        let o = if self.recompute_attention && super::attention::supported(&qkv) {
            super::attention::attention(&qkv, h, scale)?
        } else if self.recompute_attention {
            super::attention::attention_portable(&qkv, h, scale)?
        } else {
            let qkv = qkv.reshape((b, t, 3, h, hd))?.permute((2, 0, 3, 1, 4))?;
            let q = qkv.get(0)?.contiguous()?;
            let k = qkv.get(1)?.contiguous()?;
            let v = qkv.get(2)?.contiguous()?;
            let att = (q.matmul(&k.t()?)? * scale)?;
            let att = softmax_last(&att)?;
            att.matmul(&v)?.transpose(1, 2)?.reshape((b, t, d))?
        };
        let a = self.proj.forward(&o, dropout)?.broadcast_mul(&self.ls1)?;
        let x = (x + a)?;
        let m = self.fc1.forward(&self.norm2.forward(&x)?, dropout)?;
        let m = super::gelu::gelu_erf(&m)?;
        let m = self.fc2.forward(&m, dropout)?.broadcast_mul(&self.ls2)?;
        x + m
    }

    fn linear_mut(&mut self, target: LoraTarget) -> &mut TLinear {
        match target {
            LoraTarget::Q | LoraTarget::K | LoraTarget::V => &mut self.qkv,
            LoraTarget::Proj => &mut self.proj,
            LoraTarget::Fc1 => &mut self.fc1,
            LoraTarget::Fc2 => &mut self.fc2,
        }
    }
}

/// `F.interpolate(scale_factor, mode="bicubic", align_corners=False)` along one axis as an
/// `(out, in)` matrix, with the taps of [`crate::candle::dinov2::interpolate_bicubic_scale_factor`].
/// The taps are f32 whatever the network's dtype: the official DINOv2 interpolates the position
/// embeddings in f32 (`self.pos_embed.float()`) also in an f64 model.
fn bicubic_matrix(in_len: usize, scale: f64) -> (usize, Vec<f64>) {
    let out_len = (in_len as f64 * scale).floor() as usize;
    let inv = (1.0 / scale) as f32;
    let last = in_len as i64 - 1;
    let mut m = vec![0.0f64; out_len * in_len];
    for d in 0..out_len {
        let real = inv * (d as f32 + 0.5) - 0.5;
        let i0 = real.floor();
        let w = torch_cubic_coefficients(real - i0);
        let i0 = i0 as i64;
        for (k, wk) in w.iter().enumerate() {
            let i = (i0 - 1 + k as i64).clamp(0, last) as usize;
            m[d * in_len + i] += f64::from(*wk);
        }
    }
    (out_len, m)
}

/// Bilinear `align_corners=True` resampling along one axis as an `(out, in)` matrix (taps in f32
/// as PyTorch for f32 tensors; in f64 when `f64_taps`, as PyTorch for f64 tensors).
fn bilinear_ac_matrix(in_len: usize, out_len: usize, f64_taps: bool) -> Vec<f64> {
    let mut m = vec![0.0f64; out_len * in_len];
    for (d, (i0, i1, w0, w1)) in super::resample::taps(in_len, out_len, f64_taps)
        .into_iter()
        .enumerate()
    {
        m[d * in_len + i0] += w0;
        m[d * in_len + i1] += w1;
    }
    m
}

fn matrix(values: Vec<f64>, rows: usize, cols: usize, like: &Tensor) -> Result<Tensor> {
    Tensor::from_vec(values, (rows, cols), like.device())?.to_dtype(like.dtype())
}

/// Bilinear `align_corners=True` upsampling of `(B, C, h, w)` to `(B, C, oh, ow)`: `Rh · X · Rwᵀ`.
/// CPU f32/f64: the two-tap kernel of [`super::resample`]; elsewhere the matrix products.
pub(crate) fn upsample_bilinear_ac(x: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    if super::resample::supported(x) {
        return super::resample::upsample(x, oh, ow);
    }
    let (b, c, h, w) = x.dims4()?;
    let f64_taps = x.dtype() == DType::F64;
    let rw = matrix(bilinear_ac_matrix(w, ow, f64_taps), ow, w, x)?;
    let rh = matrix(bilinear_ac_matrix(h, oh, f64_taps), oh, h, x)?;
    let rw2 = rw.clone();
    let y = frozen(
        &x.reshape((b * c * h, w))?,
        move |x| x.matmul(&rw.t()?),
        move |g| g.matmul(&rw2),
    )?; // (B·C·h, ow)
    let rh2 = rh.clone();
    let y = frozen(
        &y.reshape((b * c, h, ow))?,
        move |y| rh.broadcast_matmul(y),
        move |g| rh2.t()?.broadcast_matmul(g),
    )?; // (B·C, oh, ow)
    y.reshape((b, c, oh, ow))
}

#[derive(Debug, Clone)]
struct TConv {
    w: Tensor,
    b: Option<Tensor>,
    stride: usize,
    padding: usize,
}

impl TConv {
    fn new(
        src: &mut ParamSource,
        (c_in, c_out, k): (usize, usize, usize),
        stride: usize,
        bias: bool,
    ) -> Result<Self> {
        Ok(Self {
            w: src.get((c_out, c_in, k, k), "weight")?,
            b: if bias {
                Some(src.get(c_out, "bias")?)
            } else {
                None
            },
            stride,
            padding: k / 2,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (_, _, kh, _) = self.w.dims4()?;
        let y = if kh == 1 {
            // 1×1 convolution as a matmul over channels.
            let (b, c, h, w) = x.dims4()?;
            let wm = self.w.squeeze(3)?.squeeze(2)?;
            let c_out = wm.dim(0)?;
            let x = x.reshape((b, c, h * w))?;
            let y = if self.w.is_variable() {
                wm.broadcast_matmul(&x)?
            } else {
                let wm2 = wm.clone();
                frozen(
                    &x,
                    move |x| wm.broadcast_matmul(x),
                    move |g| wm2.t()?.broadcast_matmul(g),
                )?
            };
            y.reshape((b, c_out, h, w))?
        } else if self.stride == 1 {
            if let Some(b) = self.b.as_ref().filter(|b| !b.track_op()) {
                // Frozen bias: added inside the convolution kernel (a constant, no gradient).
                return self.conv_stride1_bias(x, Some(b));
            }
            self.conv_stride1(x)?
        } else {
            // candle 0.11's conv2d backward gets the input gradient's width wrong for strided
            // convolutions whose height and width need different output paddings (it uses the
            // height's for both). Stride s = stride-1 convolution, then every s-th row and column.
            let y = self.conv_stride1(x)?;
            let (_, _, h, w) = y.dims4()?;
            let pick = |n: usize| -> Result<Tensor> {
                let idx: Vec<u32> = (0..n as u32).step_by(self.stride).collect();
                Tensor::from_vec(idx.clone(), idx.len(), y.device())
            };
            y.index_select(&pick(h)?, 2)?.index_select(&pick(w)?, 3)?
        };
        match &self.b {
            Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
            None => Ok(y),
        }
    }
}

impl TConv {
    /// Stride-1 convolution; a frozen kernel gets no gradient (its input does: the transposed
    /// convolution, as candle's backward computes it).
    fn conv_stride1(&self, x: &Tensor) -> Result<Tensor> {
        self.conv_stride1_bias(x, None)
    }

    /// [`Self::conv_stride1`] plus a frozen `bias` (`(c_out)`, no gradient).
    fn conv_stride1_bias(&self, x: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
        let p = self.padding;
        let add = |y: Tensor| -> Result<Tensor> {
            match bias {
                Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
                None => Ok(y),
            }
        };
        if self.w.is_variable() {
            return add(x.conv2d(&self.w, p, 1, 1, 1)?);
        }
        let (_, _, kh, kw) = self.w.dims4()?;
        if (kh, kw, p) == (3, 3, 1) {
            let b1 = bias.cloned();
            // The inference path's im2col + gemm kernel for both directions: the adjoint of a
            // stride-1, padding-1 3×3 convolution is the same convolution with the kernel's
            // input and output channels swapped and both spatial axes reversed.
            let w1 = self.w.clone();
            let w2 = flipped_transposed_kernel(&self.w)?;
            return frozen(
                x,
                move |x| conv3x3_same(x, &w1, b1.as_ref()),
                move |g| conv3x3_same(g, &w2, None),
            );
        }
        let (w1, w2) = (self.w.clone(), self.w.clone());
        add(frozen(
            x,
            move |x| x.conv2d(&w1, p, 1, 1, 1),
            move |g| g.conv_transpose2d(&w2, p, 0, 1, 1),
        )?)
    }
}

/// `w'[i, o, 2 − y, 2 − x] = w[o, i, y, x]` for a `(c_out, c_in, 3, 3)` kernel `w`: the kernel
/// of the adjoint (transposed) stride-1, padding-1 convolution.
fn flipped_transposed_kernel(w: &Tensor) -> Result<Tensor> {
    let (_, _, kh, kw) = w.dims4()?;
    let rev = |n: usize| Tensor::from_vec((0..n as u32).rev().collect::<Vec<_>>(), n, w.device());
    w.transpose(0, 1)?
        .contiguous()?
        .index_select(&rev(kh)?, 2)?
        .index_select(&rev(kw)?, 3)?
        .contiguous()
}

/// Stride-1, padding-1 3×3 convolution with an optional (constant) bias on `(B, C, H, W)` with the inference
/// kernel ([`crate::candle::ops::conv3x3`]: im2col + gemm on CPU f32, candle's `conv2d`
/// elsewhere), one image at a time.
fn conv3x3_same(x: &Tensor, w: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let fused = crate::candle::ops::ConvFusion::default();
    let b = x.dim(0)?;
    if b == 1 {
        return crate::candle::ops::conv3x3(x, w, bias, 1, fused);
    }
    let ys = (0..b)
        .map(|i| crate::candle::ops::conv3x3(&x.narrow(0, i, 1)?, w, bias, 1, fused))
        .collect::<Result<Vec<_>>>()?;
    Tensor::cat(&ys, 0)
}

/// `ConvTranspose2d(c, c, k, stride=k)`: one matmul and a reshuffle.
#[derive(Debug, Clone)]
struct TPatchExpand {
    w: Tensor,
    b: Tensor,
    k: usize,
}

impl TPatchExpand {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let k = self.k;
        let c_out = self.w.dim(1)?;
        let wm = self.w.reshape((c, c_out * k * k))?;
        let y = x
            .reshape((b, c, h * w))?
            .transpose(1, 2)?
            .broadcast_matmul(&wm)?
            .reshape((b, h, w, c_out, k, k))?
            .permute((0, 3, 1, 4, 2, 5))?
            .reshape((b, c_out, h * k, w * k))?;
        y.broadcast_add(&self.b.reshape((1, (), 1, 1))?)
    }
}

#[derive(Debug, Clone)]
enum TResize {
    Up(TPatchExpand),
    Identity,
    Down(TConv),
}

#[derive(Debug, Clone)]
struct TRcu {
    conv1: TConv,
    conv2: TConv,
}

impl TRcu {
    fn new(src: &mut ParamSource, f: usize) -> Result<Self> {
        let conv1 = TConv::new(&mut src.pp("conv1"), (f, f, 3), 1, true)?;
        let conv2 = TConv::new(&mut src.pp("conv2"), (f, f, 3), 1, true)?;
        Ok(Self { conv1, conv2 })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let out = self.conv1.forward(&x.relu()?)?;
        let out = self.conv2.forward(&out.relu()?)?;
        out + x
    }
}

#[derive(Debug, Clone)]
struct TFusion {
    rcu1: TRcu,
    rcu2: TRcu,
    out_conv: TConv,
}

impl TFusion {
    fn forward(&self, x0: &Tensor, x1: Option<&Tensor>, size: (usize, usize)) -> Result<Tensor> {
        let mut out = x0.clone();
        if let Some(x1) = x1 {
            out = (out + self.rcu1.forward(x1)?)?;
        }
        out = self.rcu2.forward(&out)?;
        // 1×1 conv before the upsampling: both linear, bilinear weights sum to one (as inference).
        let out = self.out_conv.forward(&out)?;
        upsample_bilinear_ac(&out, size.0, size.1)
    }
}

/// A training forward's output: the prediction and, for a metric head, its natural logarithm
/// computed stably from the logits ([`TrainNet::forward_output`]).
#[derive(Debug, Clone)]
pub struct NetOutput {
    /// `(B, H, W)`: metres (metric head) or disparity (relative head).
    pub pred: Tensor,
    /// `ln pred` from the logits (metric head), `None` for a relative head.
    pub log_pred: Option<Tensor>,
}

/// A metric head's output from its logits `z`: depth `σ(z)·max_depth_m` and its logarithm
/// `ln max_depth_m + ln σ(z)` with `ln σ(z) = −relu(−z) − ln(1 + e^{−|z|})` (finite for every
/// finite `z`, gradient `σ(−z)`).
///
/// # Errors
/// Tensor errors.
pub fn metric_output(logits: &Tensor, max_depth_m: f64) -> Result<NetOutput> {
    let pred = (candle_nn::ops::sigmoid(logits)? * max_depth_m)?;
    let log_sigmoid =
        (logits.neg()?.relu()?.neg()? - ((logits.abs()?.neg()?.exp()? + 1.0)?.log()?))?;
    Ok(NetOutput {
        pred,
        log_pred: Some((log_sigmoid + max_depth_m.ln())?),
    })
}

/// The training network. Build with [`TrainNet::new`], add adapters with [`TrainNet::add_lora`].
#[derive(Debug)]
pub struct TrainNet {
    config: DepthAnythingConfig,
    patch_w: Tensor,
    patch_b: Tensor,
    cls_token: Tensor,
    pos_embed: Tensor,
    blocks: Vec<TBlock>,
    norm: Ln,
    projects: Vec<TConv>,
    resize: Vec<TResize>,
    layer_rn: Vec<TConv>,
    refine: Vec<TFusion>,
    output_conv1: TConv,
    output_conv2_0: TConv,
    output_conv2_2: TConv,
    base_vars: BTreeMap<String, Var>,
    lora_vars: BTreeMap<String, Var>,
    lora_config: Option<LoraConfig>,
    dropout: Dropout,
    /// Forces the operations a GPU runs, also on the CPU ([`Self::set_portable_ops`]).
    portable_ops: bool,
}

impl TrainNet {
    /// Builds the network from `src` (root holding `pretrained.*` and `depth_head.*`); the
    /// tensors `src` marks trainable become variables ([`Self::base_vars`]).
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(config: &DepthAnythingConfig, mut src: ParamSource) -> Result<Self> {
        let cfg = config;
        let d = cfg.embed_dim;
        let p = PATCH_SIZE;
        let g = cfg.pos_grid;
        let (patch_w, patch_b, cls_token, pos_embed, blocks, norm) = {
            let mut e = src.pp("pretrained");
            let patch_w = e.get((d, 3, p, p), "patch_embed.proj.weight")?;
            let patch_b = e.get(d, "patch_embed.proj.bias")?;
            let cls_token = e.get((1, 1, d), "cls_token")?;
            let pos_embed = e.get((1, 1 + g * g, d), "pos_embed")?;
            let blocks = (0..cfg.depth)
                .map(|i| TBlock::new(&mut e.pp(&format!("blocks.{i}")), cfg))
                .collect::<Result<Vec<_>>>()?;
            let norm = Ln::new(&mut e.pp("norm"), d, cfg.layer_norm_eps)?;
            (patch_w, patch_b, cls_token, pos_embed, blocks, norm)
        };
        let oc = cfg.out_channels;
        let f = cfg.features;
        let mut h = src.pp("depth_head");
        let projects = (0..4)
            .map(|i| TConv::new(&mut h.pp(&format!("projects.{i}")), (d, oc[i], 1), 1, true))
            .collect::<Result<Vec<_>>>()?;
        let expand = |h: &mut ParamSource, i: usize, k: usize| -> Result<TResize> {
            let mut s = h.pp(&format!("resize_layers.{i}"));
            Ok(TResize::Up(TPatchExpand {
                w: s.get((oc[i], oc[i], k, k), "weight")?,
                b: s.get(oc[i], "bias")?,
                k,
            }))
        };
        let resize = vec![
            expand(&mut h, 0, 4)?,
            expand(&mut h, 1, 2)?,
            TResize::Identity,
            TResize::Down(TConv::new(
                &mut h.pp("resize_layers.3"),
                (oc[3], oc[3], 3),
                2,
                true,
            )?),
        ];
        let mut s = h.pp("scratch");
        let layer_rn = (0..4)
            .map(|i| {
                TConv::new(
                    &mut s.pp(&format!("layer{}_rn", i + 1)),
                    (oc[i], f, 3),
                    1,
                    false,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let refine = (0..4)
            .map(|i| {
                let mut r = s.pp(&format!("refinenet{}", i + 1));
                let rcu1 = TRcu::new(&mut r.pp("resConfUnit1"), f)?;
                let rcu2 = TRcu::new(&mut r.pp("resConfUnit2"), f)?;
                let out_conv = TConv::new(&mut r.pp("out_conv"), (f, f, 1), 1, true)?;
                Ok(TFusion {
                    rcu1,
                    rcu2,
                    out_conv,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let output_conv1 = TConv::new(&mut s.pp("output_conv1"), (f, f / 2, 3), 1, true)?;
        let output_conv2_0 = TConv::new(&mut s.pp("output_conv2.0"), (f / 2, 32, 3), 1, true)?;
        let output_conv2_2 = TConv::new(&mut s.pp("output_conv2.2"), (32, 1, 1), 1, true)?;
        drop(s);
        drop(h);
        Ok(Self {
            config: cfg.clone(),
            patch_w,
            patch_b,
            cls_token,
            pos_embed,
            blocks,
            norm,
            projects,
            resize,
            layer_rn,
            refine,
            output_conv1,
            output_conv2_0,
            output_conv2_2,
            base_vars: std::mem::take(&mut src.vars),
            lora_vars: BTreeMap::new(),
            lora_config: None,
            dropout: Dropout::new(0.0, 0),
            portable_ops: false,
        })
    }

    /// The architecture.
    pub fn config(&self) -> &DepthAnythingConfig {
        &self.config
    }

    /// Base weights that are trained (official key → variable).
    pub fn base_vars(&self) -> &BTreeMap<String, Var> {
        &self.base_vars
    }

    /// LoRA variables (`blocks.{i}.{target}.lora_A|lora_B` → variable).
    pub fn lora_vars(&self) -> &BTreeMap<String, Var> {
        &self.lora_vars
    }

    /// Every trained variable: LoRA, then base weights.
    pub fn all_vars(&self) -> Vec<Var> {
        self.lora_vars
            .values()
            .chain(self.base_vars.values())
            .cloned()
            .collect()
    }

    /// Turns LoRA dropout on (training) or off (evaluation).
    pub fn set_training(&mut self, on: bool) {
        self.dropout.active = on;
    }

    /// Restarts the LoRA dropout generator at `seed` (the trainer derives it from the seed and
    /// the step, so a resumed run draws the same masks as an uninterrupted one).
    pub(crate) fn reseed_dropout(&mut self, seed: u64) {
        self.dropout.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// Attention that keeps no `T × T` probabilities for the backward and recomputes them
    /// there (default on; a kernel on CPU f32/f64, candle operations elsewhere). Off: the
    /// composed softmax, whose graph keeps scores, exponentials and probabilities per block.
    pub fn set_recompute_attention(&mut self, on: bool) {
        for b in &mut self.blocks {
            b.recompute_attention = on;
        }
    }

    /// Runs the operations a GPU runs (candle operations with attached backwards: the
    /// recomputed attention, the LayerNorm, the exact GELU and the resampling) also on the CPU,
    /// instead of this crate's CPU kernels: for tests of that path and to measure its memory
    /// where no GPU is at hand. Off by default; no effect on other devices.
    pub fn set_portable_ops(&mut self, on: bool) {
        self.portable_ops = on;
    }

    /// The attached adapters' settings.
    pub fn lora_config(&self) -> Option<&LoraConfig> {
        self.lora_config.as_ref()
    }

    /// Adds LoRA adapters to every block as `lora` says: A Kaiming-uniform (a = √5, bound
    /// 1/√in as HF peft), B zeros, seeded by `lora.seed`.
    ///
    /// # Errors
    /// Rank 0 or larger than the layer, alpha ≤ 0, adapters already present.
    pub fn add_lora(&mut self, lora: &LoraConfig) -> Result<()> {
        lora.validate(&self.config)
            .map_err(candle_core::Error::Msg)?;
        if !self.lora_vars.is_empty() {
            candle_core::bail!("LoRA adapters are already attached");
        }
        let mut rng = ChaCha8Rng::seed_from_u64(lora.seed);
        let dtype = self.patch_w.dtype();
        let device = self.patch_w.device().clone();
        let r = lora.rank;
        let scale = lora.alpha / r as f64;
        let d = self.config.embed_dim;
        let hidden = self.config.mlp_hidden_dim;
        let targets: BTreeSet<LoraTarget> = lora.targets.iter().copied().collect();
        for (i, block) in self.blocks.iter_mut().enumerate() {
            for &t in &targets {
                let (in_dim, rows, offset) = t.shape(d, hidden);
                let bound = 1.0 / (in_dim as f64).sqrt();
                let a: Vec<f64> = (0..r * in_dim)
                    .map(|_| rng.random_range(-bound..bound))
                    .collect();
                let a =
                    Var::from_tensor(&Tensor::from_vec(a, (r, in_dim), &device)?.to_dtype(dtype)?)?;
                let b = Var::zeros((rows, r), dtype, &device)?;
                let key = format!("blocks.{i}.{}", t.key());
                self.lora_vars.insert(format!("{key}.lora_A"), a.clone());
                self.lora_vars.insert(format!("{key}.lora_B"), b.clone());
                block.linear_mut(t).lora.push(LoraPart {
                    a,
                    b,
                    offset,
                    scale,
                });
            }
        }
        self.dropout = Dropout::new(lora.dropout, lora.seed ^ 0x9e37_79b9_7f4a_7c15);
        self.lora_config = Some(lora.clone());
        Ok(())
    }

    /// The attached adapters and every trained base tensor (the head with `--train-head`) as an
    /// [`Adapter`] (values copied to f32 on the CPU): everything training changed reaches
    /// inference through it.
    ///
    /// # Errors
    /// No adapters attached.
    pub fn adapter(&self, base_fingerprint: &str, settings: serde_json::Value) -> Result<Adapter> {
        let Some(lora) = &self.lora_config else {
            candle_core::bail!("no LoRA adapters attached");
        };
        // Values copied to f32 on the CPU, by name.
        let copy = |vars: &BTreeMap<String, Var>| {
            vars.iter()
                .map(|(k, v)| {
                    let t = v
                        .as_tensor()
                        .detach()
                        .to_dtype(DType::F32)?
                        .to_device(&Device::Cpu)?;
                    Ok((k.clone(), t))
                })
                .collect::<Result<BTreeMap<_, _>>>()
        };
        let tensors = copy(&self.lora_vars)?;
        let base = copy(&self.base_vars)?;
        Ok(Adapter {
            lora: lora.clone(),
            arch: (
                self.config.embed_dim,
                self.config.depth,
                self.config.mlp_hidden_dim,
            ),
            base_fingerprint: base_fingerprint.to_string(),
            settings,
            tensors,
            base,
            head: Some(self.config.head),
        })
    }

    /// Sets the attached adapters' matrices from `adapter` (same rank and targets), e.g. to resume.
    ///
    /// # Errors
    /// Different rank, alpha or targets; shape mismatches.
    pub fn set_lora_values(&mut self, adapter: &Adapter) -> Result<()> {
        let Some(lora) = &self.lora_config else {
            candle_core::bail!("no LoRA adapters attached");
        };
        if lora.rank != adapter.lora.rank
            || lora.alpha != adapter.lora.alpha
            || lora.targets != adapter.lora.targets
        {
            candle_core::bail!(
                "adapter has rank {}, alpha {}, targets {:?}; this run rank {}, alpha {}, targets {:?}",
                adapter.lora.rank,
                adapter.lora.alpha,
                adapter.lora.targets,
                lora.rank,
                lora.alpha,
                lora.targets
            );
        }
        for (k, v) in &self.lora_vars {
            let Some(t) = adapter.tensors.get(k) else {
                candle_core::bail!("adapter lacks {k}");
            };
            v.set(&t.to_dtype(v.dtype())?.to_device(v.device())?)?;
        }
        Ok(())
    }

    /// Position embeddings for a `rows × cols` grid: `(1, 1 + rows·cols, dim)`.
    fn pos_embed_for(&self, rows: usize, cols: usize) -> Result<Tensor> {
        let g = self.config.pos_grid;
        if rows == g && cols == g {
            return Ok(self.pos_embed.clone());
        }
        let d = self.config.embed_dim;
        let cls = self.pos_embed.narrow(1, 0, 1)?;
        let grid = self.pos_embed.narrow(1, 1, g * g)?.reshape((g, g * d))?;
        let (r_out, wr) =
            bicubic_matrix(g, (rows as f64 + POS_EMBED_INTERPOLATE_OFFSET) / g as f64);
        let (c_out, wc) =
            bicubic_matrix(g, (cols as f64 + POS_EMBED_INTERPOLATE_OFFSET) / g as f64);
        if r_out != rows || c_out != cols {
            candle_core::bail!(
                "position-embedding interpolation gave a {r_out}x{c_out} grid, expected {rows}x{cols}"
            );
        }
        let wr = matrix(wr, rows, g, &grid)?;
        let wc = matrix(wc, cols, g, &grid)?;
        let t = wr.matmul(&grid)?.reshape((rows, g, d))?;
        let t = wc.broadcast_matmul(&t)?.reshape((1, rows * cols, d))?;
        Tensor::cat(&[&cls, &t], 1)
    }

    /// The network on `(B, 3, H, W)` (H, W multiples of 14, ImageNet-normalised) → `(B, H, W)`:
    /// inverse depth (relative head) or metres (metric head). Differentiable in every variable.
    ///
    /// # Errors
    /// Shape errors.
    pub fn forward(&mut self, x: &Tensor) -> Result<Tensor> {
        Ok(self.forward_output(x)?.pred)
    }

    /// As [`Self::forward`], with the logarithm of a metric head's depth computed from its
    /// logits `z`: `ln d = ln max_depth + ln σ(z)`, where `ln σ(z) = −relu(−z) − ln(1 + e^{−|z|})`
    /// is finite for every finite `z`. In f32, `σ(z)` is exactly 0 below `z ≈ −104` (and
    /// subnormal below −87), so `ln(σ(z)·max)` of the depth is −∞ there and a log loss turns NaN
    /// with an infinite gradient; the log-sigmoid keeps both finite (its gradient is
    /// `σ(−z) ≤ 1`). This is what the training losses take (see [`super::loss::loss_of`]).
    ///
    /// # Errors
    /// Shape errors.
    pub fn forward_output(&mut self, x: &Tensor) -> Result<NetOutput> {
        let _portable = super::PortableScope::enter(self.portable_ops);
        let x = x.to_dtype(self.patch_w.dtype())?;
        let (b, c, h, w) = x.dims4()?;
        let p = PATCH_SIZE;
        if c != 3 || h % p != 0 || w % p != 0 || h == 0 || w == 0 {
            candle_core::bail!(
                "training network expects (B, 3, 14·k, 14·l), got {:?}",
                x.dims()
            );
        }
        let (rows, cols) = (h / p, w / p);
        let d = self.config.embed_dim;
        let patches = x
            .reshape((b, c, rows, p, cols, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .reshape((b, rows * cols, c * p * p))?;
        let tokens = patches
            .broadcast_matmul(&self.patch_w.reshape((d, c * p * p))?.t()?)?
            .broadcast_add(&self.patch_b)?;
        let cls = self.cls_token.broadcast_as((b, 1, d))?;
        let mut xs = Tensor::cat(&[&cls, &tokens], 1)?;
        xs = xs.broadcast_add(&self.pos_embed_for(rows, cols)?)?;
        let layers = self.config.intermediate_layers;
        let last = layers.iter().copied().max().unwrap_or(0);
        let mut feats: Vec<Option<Tensor>> = vec![None; 4];
        for i in 0..=last {
            xs = self.blocks[i].forward(&xs, &mut self.dropout)?;
            for (j, &l) in layers.iter().enumerate() {
                if l == i {
                    feats[j] = Some(self.norm.forward(&xs)?.narrow(1, 1, rows * cols)?);
                }
            }
        }
        let mut maps = Vec::with_capacity(4);
        for (j, f) in feats.into_iter().enumerate() {
            let Some(tokens) = f else {
                candle_core::bail!("intermediate layer {} missing", layers[j]);
            };
            let t = tokens.transpose(1, 2)?.reshape((b, d, rows, cols))?;
            let t = self.projects[j].forward(&t)?;
            let t = match &self.resize[j] {
                TResize::Up(m) => m.forward(&t)?,
                TResize::Identity => t,
                TResize::Down(m) => m.forward(&t)?,
            };
            maps.push(self.layer_rn[j].forward(&t)?);
        }
        let size = |t: &Tensor| -> Result<(usize, usize)> {
            let (_, _, h, w) = t.dims4()?;
            Ok((h, w))
        };
        let path4 = self.refine[3].forward(&maps[3], None, size(&maps[2])?)?;
        let path3 = self.refine[2].forward(&path4, Some(&maps[2]), size(&maps[1])?)?;
        let path2 = self.refine[1].forward(&path3, Some(&maps[1]), size(&maps[0])?)?;
        let (h0, w0) = size(&maps[0])?;
        let path1 = self.refine[0].forward(&path2, Some(&maps[0]), (2 * h0, 2 * w0))?;
        let out = self.output_conv1.forward(&path1)?;
        let out = upsample_bilinear_ac(&out, h, w)?;
        let out = self.output_conv2_0.forward(&out)?.relu()?;
        let out = self.output_conv2_2.forward(&out)?;
        let out = out.squeeze(1)?;
        Ok(match self.config.head {
            Head::Relative => NetOutput {
                pred: out.relu()?,
                log_pred: None,
            },
            Head::Metric { max_depth_m } => metric_output(&out, f64::from(max_depth_m))?,
        })
    }
}

/// The device and dtype of a built network (for callers that create inputs).
impl TrainNet {
    /// Device of the weights.
    pub fn device(&self) -> &Device {
        self.patch_w.device()
    }

    /// Dtype of the weights.
    pub fn dtype(&self) -> DType {
        self.patch_w.dtype()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(shape: &[usize], seed: u64, dtype: DType) -> Tensor {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n: usize = shape.iter().product();
        let v: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        Tensor::from_vec(v, shape, &Device::Cpu)
            .and_then(|t| t.to_dtype(dtype))
            .unwrap()
    }

    fn max_rel(a: &Tensor, b: &Tensor) -> f64 {
        let a: Vec<f64> = a
            .flatten_all()
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_vec1()
            .unwrap();
        let b: Vec<f64> = b
            .flatten_all()
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_vec1()
            .unwrap();
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        a.iter()
            .zip(&b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
            / scale
    }

    /// A frozen 3×3 convolution on the im2col kernel (f32, batch 2, odd sizes): forward equals
    /// candle's `conv2d`, the input gradient equals candle's `conv_transpose2d` of the output
    /// gradient (the adjoint), and the frozen kernel gets no gradient.
    #[test]
    fn frozen_conv3x3_matches_candle_forward_and_transposed_backward() {
        let w = random(&[4, 5, 3, 3], 1, DType::F32);
        let conv = TConv {
            w: w.clone(),
            b: None,
            stride: 1,
            padding: 1,
        };
        let x = Var::from_tensor(&random(&[2, 5, 7, 9], 2, DType::F32)).unwrap();
        let r = random(&[2, 4, 7, 9], 3, DType::F32);
        let y = conv.forward(x.as_tensor()).unwrap();
        let want = x.as_tensor().conv2d(&w, 1, 1, 1, 1).unwrap();
        assert!(max_rel(&y, &want) < 1e-6, "forward {}", max_rel(&y, &want));
        let grads = (y * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let gx = grads.get(x.as_tensor()).unwrap();
        let want = r.conv_transpose2d(&w, 1, 0, 1, 1).unwrap();
        assert!(max_rel(gx, &want) < 1e-6, "backward {}", max_rel(gx, &want));
        assert!(grads.get(&w).is_none());
    }

    /// The same frozen convolution in f64: its input gradient equals central finite differences
    /// of `Σ conv(x) ⊙ r` (every input entry of one image).
    #[test]
    fn frozen_conv3x3_input_gradient_matches_finite_differences_in_f64() {
        let w = random(&[3, 2, 3, 3], 4, DType::F64);
        let conv = TConv {
            w,
            b: None,
            stride: 1,
            padding: 1,
        };
        let shape = [1, 2, 4, 5];
        let x0: Vec<f64> = random(&shape, 5, DType::F64)
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let r = random(&[1, 3, 4, 5], 6, DType::F64);
        crate::candle::train::testing::check_input_gradient(
            "frozen conv3x3",
            |x| conv.forward(x).unwrap(),
            &x0,
            &shape,
            &r,
            crate::candle::train::testing::FdCheck::EVERY_ENTRY,
        );
    }
}
