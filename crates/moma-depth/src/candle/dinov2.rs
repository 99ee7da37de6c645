//! The DINOv2 ViT encoder of Depth Anything V2 (`depth_anything_v2/dinov2.py`, commit a561b84):
//! patch embedding (conv 14×14, stride 14), class token, position embedding with the exact
//! bicubic interpolation rule of docs/method.md §5, pre-norm blocks with LayerScale, LayerNorm eps
//! 1e-6 and exact-erf GELU, and `get_intermediate_layers(..., norm=True)`.

use std::collections::HashMap;

use candle_core::{DType, Module, Result, Tensor};
use candle_nn::VarBuilder;

use super::DepthAnythingConfig;
use crate::preprocess::{CUBIC_A, PATCH_SIZE};

/// Offset added to the patch-grid size before computing the interpolation scale
/// (`interpolate_offset=0.1` in `depth_anything_v2/dinov2.py::DINOv2`).
pub const POS_EMBED_INTERPOLATE_OFFSET: f64 = 0.1;

/// LayerNorm with the weights of one `nn.LayerNorm(dim, eps)`.
#[derive(Debug, Clone)]
pub(crate) struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f32,
}

impl LayerNorm {
    pub(crate) fn new(dim: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get(dim, "weight")?,
            bias: vb.get(dim, "bias")?,
            eps: eps as f32,
        })
    }
}

impl Module for LayerNorm {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        super::ops::layer_norm(xs, &self.weight, &self.bias, self.eps)
    }
}

/// The precision of the encoder's products on the CPU ([`DinoV2::pack`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum PackedPrecision {
    /// f32 (`gemm`).
    F32,
    /// int8 weights and activations, `i32` sums ([`super::int8`]).
    Int8,
    /// bf16 weights and activations, `f32` sums ([`super::bf16`]).
    Bf16,
}

/// `nn.Linear` applied to `(tokens, in)` matrices: `x · Wᵀ + b`.
#[derive(Debug, Clone)]
pub(crate) struct Linear {
    /// `(in, out)`, stored transposed and contiguous once at load time.
    weight_t: Tensor,
    bias: Tensor,
    /// The same layer packed for a low-precision CPU kernel (`--dtype int8|bf16`), used
    /// instead of `weight_t` when present.
    packed: Option<std::sync::Arc<dyn super::ops::PackedLinear>>,
}

impl Linear {
    pub(crate) fn new(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get((out_dim, in_dim), "weight")?;
        Ok(Self {
            weight_t: weight.t()?.contiguous()?,
            bias: vb.get(out_dim, "bias")?,
            packed: None,
        })
    }

    /// Packs the layer for the low-precision kernel `L` ([`super::int8`],
    /// [`super::bf16`]); f32 weights on the CPU only.
    fn pack<L: super::ops::PackedLinear + 'static>(&mut self) -> Result<()> {
        let (k, n) = self.weight_t.dims2()?;
        let w = self.weight_t.flatten_all()?.to_vec1::<f32>()?;
        let b = self.bias.to_vec1::<f32>()?;
        self.packed = Some(std::sync::Arc::new(L::pack(&w, k, n, &b)?));
        // the f32 weights are not read again: freed (85 MB of a ViT-S, 1.2 GB of a ViT-L)
        self.weight_t = Tensor::zeros((0, n), candle_core::DType::F32, self.weight_t.device())?;
        Ok(())
    }
}

impl Linear {
    /// Folds a LayerScale `gamma ⊙ (x·Wᵀ + b)` into the weights: `x·(W·diag γ)ᵀ + γ ⊙ b`.
    fn scaled(self, gamma: &Tensor) -> Result<Self> {
        Ok(Self {
            weight_t: self.weight_t.broadcast_mul(gamma)?.contiguous()?,
            bias: (self.bias * gamma)?,
            packed: None,
        })
    }

    /// `[residual +] act(x·Wᵀ + b)`, fused on the CPU.
    fn forward_fused(
        &self,
        xs: &Tensor,
        residual: Option<&Tensor>,
        act: super::ops::Activation,
    ) -> Result<Tensor> {
        if let Some(layer) = &self.packed {
            return super::ops::linear_packed(xs, layer.as_ref(), residual, act);
        }
        super::ops::linear(xs, &self.weight_t, &self.bias, residual, act)
    }
}

impl Module for Linear {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.forward_fused(xs, None, super::ops::Activation::None)
    }
}

/// Multi-head self-attention (`dinov2_layers/attention.py::Attention`; `MemEffAttention` computes
/// the same without xformers).
#[derive(Debug, Clone)]
struct Attention {
    qkv: Linear,
    proj: Linear,
    num_heads: usize,
    scale: f64,
    /// The precision of both attention products (`--dtype int8|bf16`; f32 otherwise).
    packed: PackedPrecision,
}

impl Attention {
    fn new(dim: usize, num_heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            qkv: Linear::new(dim, 3 * dim, vb.pp("qkv"))?,
            proj: Linear::new(dim, dim, vb.pp("proj"))?,
            num_heads,
            scale: 1.0 / ((dim / num_heads) as f64).sqrt(),
            packed: PackedPrecision::F32,
        })
    }

    /// `residual + proj(attn(xs))` for `xs`: `(tokens, dim)` (LayerScale folded into `proj`).
    fn forward(&self, xs: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let qkv = self.qkv.forward(xs)?;
        // softmax((q·scale)·kᵀ) is computed as softmax(scale·(q·kᵀ)).
        let (heads, scale) = (self.num_heads, self.scale as f32);
        let out = match self.packed {
            PackedPrecision::F32 => super::ops::attention(&qkv, heads, scale)?,
            PackedPrecision::Int8 => {
                super::ops::attention_packed::<super::int8::QuantLinear>(&qkv, heads, scale)?
            }
            PackedPrecision::Bf16 => {
                super::ops::attention_packed::<super::bf16::Bf16Linear>(&qkv, heads, scale)?
            }
        };
        self.proj
            .forward_fused(&out, Some(residual), super::ops::Activation::None)
    }
}

/// `Mlp`: fc1 → exact GELU → fc2.
#[derive(Debug, Clone)]
struct Mlp {
    fc1: Linear,
    fc2: Linear,
}

impl Mlp {
    fn new(dim: usize, hidden: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            fc1: Linear::new(dim, hidden, vb.pp("fc1"))?,
            fc2: Linear::new(hidden, dim, vb.pp("fc2"))?,
        })
    }
}

impl Mlp {
    /// `residual + fc2(gelu(fc1(xs)))` (LayerScale folded into `fc2`).
    fn forward(&self, xs: &Tensor, residual: &Tensor) -> Result<Tensor> {
        use super::ops::Activation;
        let h = self.fc1.forward_fused(xs, None, Activation::GeluErf)?;
        self.fc2.forward_fused(&h, Some(residual), Activation::None)
    }
}

/// One pre-norm transformer block with LayerScale:
/// `x = x + ls1 ⊙ attn(norm1(x)); x = x + ls2 ⊙ mlp(norm2(x))`; `ls1`/`ls2` are folded into
/// `attn.proj` and `mlp.fc2` at load time.
#[derive(Debug, Clone)]
struct Block {
    norm1: LayerNorm,
    attn: Attention,
    norm2: LayerNorm,
    mlp: Mlp,
}

impl Block {
    fn new(cfg: &DepthAnythingConfig, vb: VarBuilder) -> Result<Self> {
        let dim = cfg.embed_dim;
        let mut attn = Attention::new(dim, cfg.num_heads, vb.pp("attn"))?;
        attn.proj = attn.proj.scaled(&vb.get(dim, "ls1.gamma")?)?;
        let mut mlp = Mlp::new(dim, cfg.mlp_hidden_dim, vb.pp("mlp"))?;
        mlp.fc2 = mlp.fc2.scaled(&vb.get(dim, "ls2.gamma")?)?;
        Ok(Self {
            norm1: LayerNorm::new(dim, cfg.layer_norm_eps, vb.pp("norm1"))?,
            attn,
            norm2: LayerNorm::new(dim, cfg.layer_norm_eps, vb.pp("norm2"))?,
            mlp,
        })
    }
}

impl Module for Block {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let xs = self.attn.forward(&self.norm1.forward(xs)?, xs)?;
        self.mlp.forward(&self.norm2.forward(&xs)?, &xs)
    }
}

/// The DINOv2 encoder (`pretrained.*` keys).
#[derive(Debug)]
pub struct DinoV2 {
    patch_weight_t: Tensor,
    patch_bias: Tensor,
    cls_token: Tensor,
    /// `(1 + grid², dim)` as stored.
    pos_embed: Tensor,
    blocks: Vec<Block>,
    norm: LayerNorm,
    embed_dim: usize,
    pos_grid: usize,
    /// Interpolated position embeddings per patch grid `(rows, cols)`: `(1 + rows·cols, dim)`.
    pos_cache: HashMap<(usize, usize), Tensor>,
}

impl DinoV2 {
    /// Packs every block's linear layers (qkv, proj, MLP) and attention products for a
    /// low-precision CPU kernel: int8 ([`super::int8`]) or bf16 ([`super::bf16`]); the patch
    /// embedding, LayerNorms, softmax and GELU stay f32.
    ///
    /// # Errors
    /// Weights that are not f32 on the CPU.
    pub(crate) fn pack(&mut self, precision: PackedPrecision) -> Result<()> {
        for b in &mut self.blocks {
            for l in [
                &mut b.attn.qkv,
                &mut b.attn.proj,
                &mut b.mlp.fc1,
                &mut b.mlp.fc2,
            ] {
                match precision {
                    PackedPrecision::F32 if l.packed.is_some() => candle_core::bail!(
                        "a packed model's f32 weights were freed: load it again for f32"
                    ),
                    PackedPrecision::F32 => {}
                    PackedPrecision::Int8 => l.pack::<super::int8::QuantLinear>()?,
                    PackedPrecision::Bf16 => l.pack::<super::bf16::Bf16Linear>()?,
                }
            }
            b.attn.packed = precision;
        }
        Ok(())
    }

    pub fn new(cfg: &DepthAnythingConfig, vb: VarBuilder) -> Result<Self> {
        let dim = cfg.embed_dim;
        let p = PATCH_SIZE;
        let w = vb.get((dim, 3, p, p), "patch_embed.proj.weight")?;
        let patch_weight_t = w.reshape((dim, 3 * p * p))?.t()?.contiguous()?;
        let patch_bias = vb.get(dim, "patch_embed.proj.bias")?;
        let cls_token = vb.get((1, 1, dim), "cls_token")?.reshape((1, dim))?;
        let n_pos = 1 + cfg.pos_grid * cfg.pos_grid;
        let pos_embed = vb
            .get((1, n_pos, dim), "pos_embed")?
            .reshape((n_pos, dim))?;
        let blocks = (0..cfg.depth)
            .map(|i| Block::new(cfg, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<Vec<_>>>()?;
        let norm = LayerNorm::new(dim, cfg.layer_norm_eps, vb.pp("norm"))?;
        Ok(Self {
            patch_weight_t,
            patch_bias,
            cls_token,
            pos_embed,
            blocks,
            norm,
            embed_dim: dim,
            pos_grid: cfg.pos_grid,
            pos_cache: HashMap::new(),
        })
    }

    /// Position embeddings for a `rows × cols` patch grid (network input `14·rows × 14·cols`):
    /// `interpolate_pos_encoding` of `dinov2.py`, computed once per grid on the CPU.
    fn pos_embed_for(&mut self, rows: usize, cols: usize) -> Result<Tensor> {
        let g = self.pos_grid;
        // `if npatch == N and w == h: return self.pos_embed`
        if rows * cols == g * g && rows == cols {
            return Ok(self.pos_embed.clone());
        }
        if let Some(t) = self.pos_cache.get(&(rows, cols)) {
            return Ok(t.clone());
        }
        let dim = self.embed_dim;
        let all = self
            .pos_embed
            .to_dtype(DType::F32)?
            .to_device(&candle_core::Device::Cpu)?;
        let cls = all.narrow(0, 0, 1)?;
        let grid: Vec<f32> = all.narrow(0, 1, g * g)?.flatten_all()?.to_vec1()?;
        let scale_rows = (rows as f64 + POS_EMBED_INTERPOLATE_OFFSET) / g as f64;
        let scale_cols = (cols as f64 + POS_EMBED_INTERPOLATE_OFFSET) / g as f64;
        let out = interpolate_bicubic_scale_factor(&grid, g, g, dim, scale_rows, scale_cols);
        if out.rows != rows || out.cols != cols {
            candle_core::bail!(
                "position-embedding interpolation gave a {}x{} grid, expected {rows}x{cols}",
                out.rows,
                out.cols
            );
        }
        let patches = Tensor::from_vec(out.values, (rows * cols, dim), &candle_core::Device::Cpu)?;
        let t = Tensor::cat(&[&cls, &patches], 0)?
            .to_dtype(self.pos_embed.dtype())?
            .to_device(self.pos_embed.device())?;
        self.pos_cache.insert((rows, cols), t.clone());
        Ok(t)
    }

    /// `get_intermediate_layers(x, layers, return_class_token=True, norm=True)` for one image:
    /// `x` is `(1, 3, H, W)` (H, W multiples of 14); returns the normalised patch tokens
    /// `(rows·cols, dim)` of each requested block (0-based indices) in order.
    ///
    /// # Errors
    /// Shape errors.
    pub fn intermediate_layers(&mut self, x: &Tensor, layers: &[usize]) -> Result<Vec<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let p = PATCH_SIZE;
        if b != 1 || c != 3 || h % p != 0 || w % p != 0 {
            candle_core::bail!("DINOv2 expects (1, 3, 14·k, 14·l), got {:?}", x.dims());
        }
        let (rows, cols) = (h / p, w / p);
        // Patch embedding as one matmul: (rows·cols, 3·14·14) · (3·14·14, dim).
        let patches = x
            .reshape((c, rows, p, cols, p))?
            .permute((1, 3, 0, 2, 4))?
            .reshape((rows * cols, c * p * p))?;
        let tokens = patches
            .matmul(&self.patch_weight_t)?
            .broadcast_add(&self.patch_bias)?;
        let mut xs = Tensor::cat(&[&self.cls_token, &tokens], 0)?;
        xs = (xs + self.pos_embed_for(rows, cols)?)?;
        let last = layers.iter().copied().max().unwrap_or(0);
        let mut outputs = Vec::with_capacity(layers.len());
        for (i, block) in self.blocks.iter().enumerate().take(last + 1) {
            xs = block.forward(&xs)?;
            if layers.contains(&i) {
                outputs.push((i, self.norm.forward(&xs)?.narrow(0, 1, rows * cols)?));
            }
        }
        layers
            .iter()
            .map(|l| {
                outputs
                    .iter()
                    .find(|(i, _)| i == l)
                    .map(|(_, t)| t.clone())
                    .ok_or_else(|| {
                        candle_core::Error::Msg(format!(
                            "intermediate layer {l} >= depth {}",
                            self.blocks.len()
                        ))
                    })
            })
            .collect()
    }
}

/// Output of [`interpolate_bicubic_scale_factor`]: `(rows·cols, dim)` values, row-major grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Interpolated {
    /// Output grid rows.
    pub rows: usize,
    /// Output grid columns.
    pub cols: usize,
    /// `(rows·cols, dim)` values, row-major.
    pub values: Vec<f32>,
}

/// PyTorch `F.interpolate(x, scale_factor=(scale_rows, scale_cols), mode="bicubic",
/// align_corners=False, antialias=False)` of a `(in_rows, in_cols)` grid of `dim`-vectors stored
/// `(in_rows·in_cols, dim)` row-major.
///
/// Output size `floor(in · scale)` (in `f64`); source coordinate `src = (dst + 0.5)/scale − 0.5`
/// with `1/scale` rounded to `f32` as PyTorch's `compute_scales_value` does; Keys kernel a = −0.75;
/// taps clamped at the border; accumulation order as in PyTorch's CPU kernel (rows outer).
pub fn interpolate_bicubic_scale_factor(
    src: &[f32],
    in_rows: usize,
    in_cols: usize,
    dim: usize,
    scale_rows: f64,
    scale_cols: f64,
) -> Interpolated {
    let rows = (in_rows as f64 * scale_rows).floor() as usize;
    let cols = (in_cols as f64 * scale_cols).floor() as usize;
    let taps = |in_len: usize, out_len: usize, scale: f64| -> Vec<([usize; 4], [f32; 4])> {
        let inv = (1.0 / scale) as f32;
        let last = in_len as i64 - 1;
        (0..out_len)
            .map(|d| {
                let real = inv * (d as f32 + 0.5) - 0.5;
                let i0 = real.floor();
                let t = real - i0;
                let i0 = i0 as i64;
                let idx = [i0 - 1, i0, i0 + 1, i0 + 2].map(|i| i.clamp(0, last) as usize);
                (idx, torch_cubic_coefficients(t))
            })
            .collect()
    };
    let rt = taps(in_rows, rows, scale_rows);
    let ct = taps(in_cols, cols, scale_cols);
    let mut values = vec![0.0f32; rows * cols * dim];
    for (r, (ri, rw)) in rt.iter().enumerate() {
        for (c, (ci, cw)) in ct.iter().enumerate() {
            let out = &mut values[(r * cols + c) * dim..(r * cols + c + 1) * dim];
            for (d, o) in out.iter_mut().enumerate() {
                let mut acc = 0.0f32;
                for k in 0..4 {
                    let row = ri[k] * in_cols;
                    let mut t = 0.0f32;
                    for j in 0..4 {
                        t += src[(row + ci[j]) * dim + d] * cw[j];
                    }
                    acc += t * rw[k];
                }
                *o = acc;
            }
        }
    }
    Interpolated { rows, cols, values }
}

/// PyTorch `get_cubic_upsample_coefficients` (aten/src/ATen/native/UpSample.h), a = −0.75.
pub(crate) fn torch_cubic_coefficients(t: f32) -> [f32; 4] {
    let a = CUBIC_A;
    let conv1 = |x: f32| ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0;
    let conv2 = |x: f32| ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a;
    [conv2(t + 1.0), conv1(t), conv1(1.0 - t), conv2(2.0 - t)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bicubic_identity_and_sizes() {
        // scale 1 reproduces the grid exactly (t = 0 -> weights (0, 1, 0, 0)).
        let src: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let out = interpolate_bicubic_scale_factor(&src, 3, 4, 1, 1.0, 1.0);
        assert_eq!((out.rows, out.cols), (3, 4));
        assert_eq!(out.values, src);
        // DAv2 at 392x518 input: grid 28x37 from 37x37 with scale (28.1/37, 37.1/37).
        let src = vec![1.0f32; 37 * 37 * 2];
        let out = interpolate_bicubic_scale_factor(&src, 37, 37, 2, 28.1 / 37.0, 37.1 / 37.0);
        assert_eq!((out.rows, out.cols), (28, 37));
        let dev = out
            .values
            .iter()
            .map(|v| (v - 1.0).abs())
            .fold(0.0f32, f32::max);
        // Keys weights sum to one up to f32 round-off of the cubic polynomials.
        assert!(dev < 1e-5, "max deviation {dev}");
    }

    #[test]
    fn bicubic_hand_computed() {
        // F.interpolate(torch.tensor([[[[0., 1.]]]]), scale_factor=(1, 2), mode="bicubic",
        // align_corners=False) = [[-0.10546875, 0.2265625, 0.7734375, 1.10546875]]
        let out = interpolate_bicubic_scale_factor(&[0.0, 1.0], 1, 2, 1, 1.0, 2.0);
        let want = [-0.105_468_75_f32, 0.226_562_5, 0.773_437_5, 1.105_468_8];
        for (g, w) in out.values.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{:?}", out.values);
        }
    }
}
