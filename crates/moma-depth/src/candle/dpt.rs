//! The DPT head of Depth Anything V2 (`depth_anything_v2/dpt.py::DPTHead` and
//! `depth_anything_v2/util/blocks.py`, commit a561b84; `depth_head.*` keys).

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use super::DepthAnythingConfig;
use crate::Head;
use crate::preprocess::PATCH_SIZE;

/// Channels of the last hidden convolution of the output head (`head_features_2 = 32`).
const HEAD_FEATURES_2: usize = 32;

/// `nn.Conv2d(c_in, c_out, kernel_size=3, stride, padding=1, bias)`.
#[derive(Debug, Clone)]
struct Conv3x3 {
    weight: Tensor,
    bias: Option<Tensor>,
    stride: usize,
}

impl Conv3x3 {
    /// The bias, which the output convolutions have.
    fn bias(&self) -> Result<&Tensor> {
        self.bias
            .as_ref()
            .ok_or_else(|| candle_core::Error::Msg("a DPT output convolution without bias".into()))
    }

    fn forward_fused(&self, xs: &Tensor, fused: super::ops::ConvFusion<'_>) -> Result<Tensor> {
        super::ops::conv3x3(xs, &self.weight, self.bias.as_ref(), self.stride, fused)
    }
}

impl Module for Conv3x3 {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.forward_fused(xs, super::ops::ConvFusion::default())
    }
}

fn conv3x3(
    c_in: usize,
    c_out: usize,
    stride: usize,
    bias: bool,
    vb: VarBuilder,
) -> Result<Conv3x3> {
    Ok(Conv3x3 {
        weight: vb.get((c_out, c_in, 3, 3), "weight")?,
        bias: if bias {
            Some(vb.get(c_out, "bias")?)
        } else {
            None
        },
        stride,
    })
}

/// A 1×1 convolution stored as a `(c_out, c_in)` matrix: applied as one matmul.
#[derive(Debug, Clone)]
struct Conv1x1 {
    weight: Tensor,
    bias: Tensor,
}

impl Conv1x1 {
    fn new(c_in: usize, c_out: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb
                .get((c_out, c_in, 1, 1), "weight")?
                .reshape((c_out, c_in))?,
            bias: vb.get(c_out, "bias")?.reshape((c_out, 1))?,
        })
    }

    /// `(1, c_in, h, w)` → `(1, c_out, h, w)`.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let y = super::ops::matmul_row_bias(
            &self.weight,
            &xs.reshape((b * c, h * w))?,
            &self.bias,
            false,
        )?;
        y.reshape((b, self.weight.dim(0)?, h, w))
    }

    /// Tokens `(h·w, c_in)` → `(1, c_out, h, w)` (the `permute + reshape + conv` of `DPTHead`).
    fn forward_tokens(&self, tokens: &Tensor, h: usize, w: usize) -> Result<Tensor> {
        let y = super::ops::matmul_row_bias(&self.weight, tokens, &self.bias, true)?;
        y.reshape((1, self.weight.dim(0)?, h, w))
    }
}

/// `nn.ConvTranspose2d(c, c, kernel_size=k, stride=k, padding=0)`: non-overlapping, so each input
/// pixel writes one `k×k` block: a single matmul plus a reshuffle.
#[derive(Debug, Clone)]
struct PatchExpand {
    /// `(c_in, c_out·k·k)`.
    weight: Tensor,
    bias: Tensor,
    c_out: usize,
    k: usize,
}

impl PatchExpand {
    fn new(c: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get((c, c, k, k), "weight")?.reshape((c, c * k * k))?;
        Ok(Self {
            weight,
            bias: vb.get(c, "bias")?.reshape((1, c, 1, 1))?,
            c_out: c,
            k,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (_, c, h, w) = xs.dims4()?;
        let k = self.k;
        // (h·w, c_in) · (c_in, c_out·k·k) -> (h, w, c_out, k, k) -> (c_out, h, k, w, k)
        let y = xs.reshape((c, h * w))?.t()?.matmul(&self.weight)?;
        let y = y
            .reshape((h, w, self.c_out, k, k))?
            .permute((2, 0, 3, 1, 4))?
            .reshape((1, self.c_out, h * k, w * k))?;
        y.broadcast_add(&self.bias)
    }
}

/// The resize layer of one DPT level.
#[derive(Debug, Clone)]
enum Resize {
    Up(PatchExpand),
    Identity,
    Down(Conv3x3),
}

impl Module for Resize {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        match self {
            Self::Up(m) => m.forward(xs),
            Self::Identity => Ok(xs.clone()),
            Self::Down(m) => m.forward(xs),
        }
    }
}

/// `ResidualConvUnit` (no batch norm): `x + conv2(relu(conv1(relu(x))))`.
#[derive(Debug, Clone)]
struct ResidualConvUnit {
    conv1: Conv3x3,
    conv2: Conv3x3,
}

impl ResidualConvUnit {
    fn new(features: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv1: conv3x3(features, features, 1, true, vb.pp("conv1"))?,
            conv2: conv3x3(features, features, 1, true, vb.pp("conv2"))?,
        })
    }
}

impl Module for ResidualConvUnit {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        use super::ops::ConvFusion;
        let out = self.conv1.forward_fused(
            xs,
            ConvFusion {
                relu_in: true,
                ..ConvFusion::default()
            },
        )?;
        self.conv2.forward_fused(
            &out,
            ConvFusion {
                relu_in: true,
                residual: Some(xs),
                relu_out: false,
            },
        )
    }
}

/// `FeatureFusionBlock` (`align_corners=True`, no batch norm, `expand=False`).
#[derive(Debug, Clone)]
struct FeatureFusionBlock {
    res_conf_unit1: ResidualConvUnit,
    res_conf_unit2: ResidualConvUnit,
    out_conv: Conv1x1,
}

impl FeatureFusionBlock {
    fn new(features: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            res_conf_unit1: ResidualConvUnit::new(features, vb.pp("resConfUnit1"))?,
            res_conf_unit2: ResidualConvUnit::new(features, vb.pp("resConfUnit2"))?,
            out_conv: Conv1x1::new(features, features, vb.pp("out_conv"))?,
        })
    }

    /// `forward(x0, [x1], size)`: `size = None` doubles the resolution (`scale_factor=2`; with
    /// `align_corners=True` PyTorch then samples at `dst·(in−1)/(out−1)` like a size request).
    fn forward(
        &self,
        x0: &Tensor,
        x1: Option<&Tensor>,
        size: Option<(usize, usize)>,
    ) -> Result<Tensor> {
        let (out, (th, tw)) = self.forward_to_upsample(x0, x1, size)?;
        super::ops::upsample_bilinear_align_corners(&out, th, tw)
    }

    /// [`Self::forward`] up to its last step, the upsampling: the map to upsample and the size
    /// to upsample it to (for a caller that fuses the upsampling into its next layer).
    fn forward_to_upsample(
        &self,
        x0: &Tensor,
        x1: Option<&Tensor>,
        size: Option<(usize, usize)>,
    ) -> Result<(Tensor, (usize, usize))> {
        let mut out = x0.clone();
        if let Some(x1) = x1 {
            out = (out + self.res_conf_unit1.forward(x1)?)?;
        }
        out = self.res_conf_unit2.forward(&out)?;
        let (_, _, h, w) = out.dims4()?;
        let (th, tw) = size.unwrap_or((2 * h, 2 * w));
        // The official order is upsample, then the 1×1 `out_conv`. Both are linear and the
        // bilinear weights of every output pixel sum to one, so the 1×1 conv (bias included)
        // commutes with the upsampling: applied first, it runs on a quarter of the pixels. The
        // results differ by f32 round-off only (the parity tests hold them to the reference).
        Ok((self.out_conv.forward(&out)?, (th, tw)))
    }
}

/// The DPT head (`depth_head.*` keys).
#[derive(Debug)]
pub struct DptHead {
    projects: Vec<Conv1x1>,
    resize_layers: Vec<Resize>,
    layer_rn: Vec<Conv3x3>,
    refinenets: Vec<FeatureFusionBlock>,
    output_conv1: Conv3x3,
    output_conv2_0: Conv3x3,
    output_conv2_2: Conv1x1,
    head: Head,
}

impl DptHead {
    /// Builds the head from `vb` = `depth_head`.
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(cfg: &DepthAnythingConfig, vb: VarBuilder) -> Result<Self> {
        let oc = cfg.out_channels;
        let f = cfg.features;
        let projects = (0..4)
            .map(|i| Conv1x1::new(cfg.embed_dim, oc[i], vb.pp(format!("projects.{i}"))))
            .collect::<Result<Vec<_>>>()?;
        let rl = vb.pp("resize_layers");
        let resize_layers = vec![
            Resize::Up(PatchExpand::new(oc[0], 4, rl.pp("0"))?),
            Resize::Up(PatchExpand::new(oc[1], 2, rl.pp("1"))?),
            Resize::Identity,
            Resize::Down(conv3x3(oc[3], oc[3], 2, true, rl.pp("3"))?),
        ];
        let scratch = vb.pp("scratch");
        let layer_rn = (0..4)
            .map(|i| conv3x3(oc[i], f, 1, false, scratch.pp(format!("layer{}_rn", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        let refinenets = (0..4)
            .map(|i| FeatureFusionBlock::new(f, scratch.pp(format!("refinenet{}", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            projects,
            resize_layers,
            layer_rn,
            refinenets,
            output_conv1: conv3x3(f, f / 2, 1, true, scratch.pp("output_conv1"))?,
            output_conv2_0: conv3x3(
                f / 2,
                HEAD_FEATURES_2,
                1,
                true,
                scratch.pp("output_conv2.0"),
            )?,
            output_conv2_2: Conv1x1::new(HEAD_FEATURES_2, 1, scratch.pp("output_conv2.2"))?,
            head: cfg.head,
        })
    }

    /// Four token maps `(rows·cols, dim)` → output `(1, 1, 14·rows, 14·cols)`: inverse depth
    /// (relative head, ReLU) or depth in metres (metric head, Sigmoid × max depth).
    ///
    /// # Errors
    /// Shape errors.
    pub fn forward(&self, features: &[Tensor], rows: usize, cols: usize) -> Result<Tensor> {
        let mut layers = Vec::with_capacity(4);
        for (i, tokens) in features.iter().enumerate() {
            let x = self.projects[i].forward_tokens(tokens, rows, cols)?;
            let x = self.resize_layers[i].forward(&x)?;
            layers.push(self.layer_rn[i].forward(&x)?);
        }
        let size = |t: &Tensor| -> Result<(usize, usize)> {
            let (_, _, h, w) = t.dims4()?;
            Ok((h, w))
        };
        let path4 = self.refinenets[3].forward(&layers[3], None, Some(size(&layers[2])?))?;
        let path3 =
            self.refinenets[2].forward(&path4, Some(&layers[2]), Some(size(&layers[1])?))?;
        let path2 =
            self.refinenets[1].forward(&path3, Some(&layers[1]), Some(size(&layers[0])?))?;
        // refinenet1's upsampling fused into output_conv1; upsample, output_conv2.0 (+ ReLU)
        // and output_conv2.2 in one pass
        let (path1, (th, tw)) =
            self.refinenets[0].forward_to_upsample(&path2, Some(&layers[0]), None)?;
        let out = super::ops::upsample_conv3x3(
            &path1,
            th,
            tw,
            &self.output_conv1.weight,
            self.output_conv1.bias()?,
            false,
            None,
        )?;
        let out = super::ops::upsample_conv3x3(
            &out,
            rows * PATCH_SIZE,
            cols * PATCH_SIZE,
            &self.output_conv2_0.weight,
            self.output_conv2_0.bias()?,
            true,
            Some((&self.output_conv2_2.weight, &self.output_conv2_2.bias)),
        )?;
        match self.head {
            // output_conv2 ends in ReLU; DepthAnythingV2.forward applies F.relu once more.
            Head::Relative => out.relu(),
            // metric_depth/dpt.py: Sigmoid, then `* self.max_depth`.
            Head::Metric { max_depth_m } => candle_nn::ops::sigmoid(&out)? * f64::from(max_depth_m),
        }
    }
}
