//! The fine-tuning loop: AdamW on the LoRA matrices (and optionally the DPT head with its own
//! learning rate), a warm-up + one-cycle or poly schedule, gradient accumulation, global
//! gradient-norm clipping, a NaN/inf stop, and an optimiser state that resumes bit for bit.
//! Data preparation (moma sets, augmentation) is the caller's.

use std::fmt;
use std::str::FromStr;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

use super::adapter::{F32View, aerr, write_atomic};
use super::{LossKind, TrainNet, loss_of, valid_indices};

/// Learning-rate schedule after a linear warm-up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Schedule {
    /// Cosine annealing from the peak to 1/1000 of it (the authors' one-cycle).
    OneCycle,
    /// `(1 − t)^0.9` (Depth Anything V2).
    Poly,
}

impl fmt::Display for Schedule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::OneCycle => "one-cycle",
            Self::Poly => "poly",
        })
    }
}

impl FromStr for Schedule {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "one-cycle" | "onecycle" => Ok(Self::OneCycle),
            "poly" => Ok(Self::Poly),
            other => Err(format!(
                "unknown schedule {other:?} (expected one-cycle or poly)"
            )),
        }
    }
}

/// The learning-rate factor (of the peak) at optimiser step `step` of `total`, with `warmup`
/// linear warm-up steps.
pub fn lr_factor(schedule: Schedule, step: usize, total: usize, warmup: usize) -> f64 {
    if step < warmup {
        return (step + 1) as f64 / warmup as f64;
    }
    let span = total.saturating_sub(warmup).max(1) as f64;
    let t = ((step - warmup) as f64 / span).clamp(0.0, 1.0);
    match schedule {
        Schedule::OneCycle => 1e-3 + (1.0 - 1e-3) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()),
        Schedule::Poly => (1.0 - t).powf(0.9),
    }
}

/// One training example at network resolution.
#[derive(Debug, Clone)]
pub struct Sample {
    /// Pre-processed network input `(3, H, W)` (ImageNet-normalised, H and W multiples of 14).
    pub input: Array3<f32>,
    /// Ground-truth depth `(H, W)`, metres (0 or non-finite = none).
    pub gt_m: Array2<f32>,
    /// Optional region the loss is restricted to `(H, W)`.
    pub mask: Option<Array2<bool>>,
}

impl Sample {
    /// Flat (row-major) indices of the pixels a loss uses: ground truth finite in
    /// `[min_depth_m, max_depth_m]` and inside the mask ([`super::valid_indices`]).
    pub fn valid_pixels(&self, min_depth_m: f32, max_depth_m: f32) -> Vec<u32> {
        let g: Vec<f32> = self.gt_m.iter().copied().collect();
        let m: Option<Vec<bool>> = self.mask.as_ref().map(|m| m.iter().copied().collect());
        valid_indices(&g, m.as_deref(), min_depth_m, max_depth_m)
    }

    /// The ground truth as a loss reads it: row-major metres, non-finite values (never valid)
    /// as 0 so that no NaN enters the tensor.
    pub fn loss_target(&self) -> Vec<f32> {
        self.gt_m
            .iter()
            .map(|&v| if v.is_finite() { v } else { 0.0 })
            .collect()
    }
}

/// Optimisation settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OptimSettings {
    /// Loss.
    pub loss: LossKind,
    /// Peak learning rate of the LoRA matrices.
    pub lr: f64,
    /// Peak learning rate of the DPT head (when trained).
    pub head_lr: f64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// Optimiser steps.
    pub steps: usize,
    /// Warm-up steps.
    pub warmup: usize,
    /// Schedule after the warm-up.
    pub schedule: Schedule,
    /// Micro-batches accumulated per optimiser step.
    pub accumulate: usize,
    /// Valid ground truth: at least this depth, metres.
    pub min_depth_m: f32,
    /// Valid ground truth: at most this depth, metres.
    pub max_depth_m: f32,
    /// Largest global L2 norm of the gradients of all trained variables (larger ones are scaled
    /// down to it, as PyTorch `clip_grad_norm_`); 0 = no clipping.
    #[serde(default)]
    pub clip_grad_norm: f64,
}

/// Value of the `format` metadata key of an optimiser-state file.
pub const OPTIM_STATE_FORMAT: &str = "moma-lora-optim-v1";

/// Stream tags of [`derive_seed`].
pub mod seed_tag {
    /// The order in which an epoch visits the training frames.
    pub const ORDER: u64 = 1;
    /// Crops and augmentation of one optimiser step.
    pub const AUGMENT: u64 = 2;
    /// LoRA dropout masks of one optimiser step.
    pub const DROPOUT: u64 = 3;
}

/// A seed for stream `tag`, item `index` (an epoch, a step) of a run seeded with `seed`
/// (splitmix64 mixing). Every random draw of a training step comes from such a seed, so a run
/// resumed at step k draws exactly what the uninterrupted run drew from step k on.
pub fn derive_seed(seed: u64, tag: u64, index: u64) -> u64 {
    let mut z = seed;
    for x in [tag, index] {
        z = z
            .wrapping_add(0x9e37_79b9_7f4a_7c15)
            .wrapping_add(x.wrapping_mul(0xd1b5_4a32_d192_ed03));
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
    }
    z
}

/// The optimiser-state file written next to an adapter: `a.safetensors` → `a.optim.safetensors`.
pub fn optim_state_path(adapter: &Path) -> PathBuf {
    adapter.with_extension("optim.safetensors")
}

/// Scales the gradients of `vars` in `grads` so that their global L2 norm is at most `max_norm`,
/// as PyTorch `clip_grad_norm_` (factor `max_norm / (norm + 1e-6)` when that is below 1;
/// `max_norm` ≤ 0: no clipping). Returns the global norm before clipping (computed in f64; NaN or
/// infinite when a gradient is, and then nothing is scaled).
///
/// # Errors
/// Tensor errors.
pub fn clip_grad_norm(grads: &mut GradStore, vars: &[Var], max_norm: f64) -> Result<f64> {
    let mut sq = 0.0f64;
    for var in vars {
        if let Some(g) = grads.get(var.as_tensor()) {
            sq += g
                .to_dtype(DType::F64)?
                .sqr()?
                .sum_all()?
                .to_scalar::<f64>()?;
        }
    }
    let norm = sq.sqrt();
    if max_norm > 0.0 && norm.is_finite() {
        let coef = max_norm / (norm + 1e-6);
        if coef < 1.0 {
            for var in vars {
                if let Some(g) = grads.get(var.as_tensor()) {
                    let scaled = (g * coef)?;
                    grads.insert(var.as_tensor(), scaled);
                }
            }
        }
    }
    Ok(norm)
}

/// One AdamW parameter group: variables with their first and second moments.
struct Group {
    /// `"lora"` or `"head"`.
    kind: &'static str,
    names: Vec<String>,
    vars: Vec<Var>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    peak_lr: f64,
}

impl Group {
    fn new(
        kind: &'static str,
        vars: &std::collections::BTreeMap<String, Var>,
        peak_lr: f64,
    ) -> Result<Option<Self>> {
        if vars.is_empty() {
            return Ok(None);
        }
        let zeros = |v: &Var| v.as_tensor().zeros_like();
        Ok(Some(Self {
            kind,
            names: vars.keys().cloned().collect(),
            vars: vars.values().cloned().collect(),
            m: vars.values().map(zeros).collect::<Result<_>>()?,
            v: vars.values().map(zeros).collect::<Result<_>>()?,
            peak_lr,
        }))
    }

    /// AdamW (β 0.9/0.999, ε 1e-8, decoupled weight decay; the arithmetic of candle-nn's
    /// `AdamW`) at learning rate `lr`, step `t` (1-based).
    fn update(&mut self, grads: &GradStore, lr: f64, weight_decay: f64, t: usize) -> Result<()> {
        let (beta1, beta2, eps) = (0.9f64, 0.999f64, 1e-8);
        let t = i32::try_from(t).unwrap_or(i32::MAX);
        let scale_m = 1.0 / (1.0 - beta1.powi(t));
        let scale_v = 1.0 / (1.0 - beta2.powi(t));
        for ((theta, m), v) in self.vars.iter().zip(&mut self.m).zip(&mut self.v) {
            let Some(g) = grads.get(theta.as_tensor()) else {
                continue;
            };
            let next_m = ((&*m * beta1)? + (g * (1.0 - beta1))?)?;
            let next_v = ((&*v * beta2)? + (g.sqr()? * (1.0 - beta2))?)?;
            let m_hat = (&next_m * scale_m)?;
            let v_hat = (&next_v * scale_v)?;
            let next_theta = (theta.as_tensor() * (1.0 - lr * weight_decay))?;
            let adjusted = (m_hat / (v_hat.sqrt()? + eps)?)?;
            theta.set(&(next_theta - (adjusted * lr)?)?)?;
            *m = next_m;
            *v = next_v;
        }
        Ok(())
    }
}

/// A training run in progress.
pub struct Trainer {
    net: TrainNet,
    groups: Vec<Group>,
    settings: OptimSettings,
    step: usize,
    last_grad_norm: f64,
}

impl Trainer {
    /// AdamW over the network's LoRA variables and its trained base (head) variables, each
    /// group with its own peak learning rate.
    ///
    /// # Errors
    /// No variable to train.
    pub fn new(net: TrainNet, settings: OptimSettings) -> Result<Self> {
        let groups: Vec<Group> = [
            Group::new("lora", net.lora_vars(), settings.lr)?,
            Group::new("head", net.base_vars(), settings.head_lr)?,
        ]
        .into_iter()
        .flatten()
        .collect();
        if groups.is_empty() {
            candle_core::bail!("nothing to train: no LoRA adapters and no trained head");
        }
        Ok(Self {
            net,
            groups,
            settings,
            step: 0,
            last_grad_norm: f64::NAN,
        })
    }

    /// The network.
    pub fn net(&self) -> &TrainNet {
        &self.net
    }

    /// Optimiser steps taken.
    pub fn steps_done(&self) -> usize {
        self.step
    }

    /// Global gradient norm of the last step, before clipping (NaN before the first step).
    pub fn last_grad_norm(&self) -> f64 {
        self.last_grad_norm
    }

    fn vars(&self) -> Vec<Var> {
        self.groups
            .iter()
            .flat_map(|g| g.vars.iter().cloned())
            .collect()
    }

    fn batch_loss(&mut self, batch: &[&Sample]) -> Result<Tensor> {
        let Some(first) = batch.first() else {
            candle_core::bail!("empty batch");
        };
        let (c, h, w) = first.input.dim();
        let mut x = Vec::with_capacity(batch.len() * c * h * w);
        let mut gt = Vec::with_capacity(batch.len() * h * w);
        let mut valid = vec![];
        for (k, s) in batch.iter().enumerate() {
            if s.input.dim() != (c, h, w) || s.gt_m.dim() != (h, w) {
                candle_core::bail!(
                    "batch mixes sizes: {:?} and {:?} (ground truth {:?})",
                    first.input.dim(),
                    s.input.dim(),
                    s.gt_m.dim()
                );
            }
            x.extend(s.input.iter().copied());
            let v = s.valid_pixels(self.settings.min_depth_m, self.settings.max_depth_m);
            valid.extend(v.into_iter().map(|i| i + (k * h * w) as u32));
            gt.extend(s.loss_target());
        }
        let dev = self.net.device().clone();
        let x = Tensor::from_vec(x, (batch.len(), c, h, w), &dev)?;
        let gt = Tensor::from_vec(gt, (batch.len(), h, w), &dev)?;
        let y = self.net.forward_output(&x)?;
        loss_of(self.settings.loss, &y, &gt, &valid)
    }

    /// One optimiser step over `micro` micro-batches (gradients accumulated, loss averaged,
    /// global gradient norm clipped to [`OptimSettings::clip_grad_norm`]); returns the mean loss.
    /// LoRA dropout masks are drawn from a generator seeded by the LoRA seed and the step. A NaN
    /// or infinite loss or gradient is an error and leaves the weights as they were.
    ///
    /// # Errors
    /// Shape errors, no valid pixel, a non-finite loss or gradient norm.
    pub fn step(&mut self, micro: &[Vec<&Sample>]) -> Result<f64> {
        if let Some(seed) = self.net.lora_config().map(|l| l.seed) {
            self.net
                .reseed_dropout(derive_seed(seed, seed_tag::DROPOUT, self.step as u64));
        }
        self.net.set_training(true);
        let n = micro.len().max(1) as f64;
        let mut total = 0.0;
        let mut acc: Option<GradStore> = None;
        let vars = self.vars();
        for batch in micro {
            let l = match self.batch_loss(batch).and_then(|l| l / n) {
                Ok(l) => l,
                Err(e) => {
                    self.net.set_training(false);
                    return Err(e);
                }
            };
            let v = l.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            if !v.is_finite() {
                self.net.set_training(false);
                let what = self.output_diagnosis(batch);
                candle_core::bail!(
                    "loss is {} at step {}: {what}; stopping (the last saved adapter is kept)",
                    v * n,
                    self.step + 1
                );
            }
            total += v;
            let g = l.backward()?;
            match &mut acc {
                None => acc = Some(g),
                Some(store) => {
                    for var in &vars {
                        if let Some(new) = g.get(var.as_tensor()) {
                            let sum = match store.get(var.as_tensor()) {
                                Some(old) => (old + new)?,
                                None => new.clone(),
                            };
                            store.insert(var.as_tensor(), sum);
                        }
                    }
                }
            }
        }
        self.net.set_training(false);
        let Some(mut grads) = acc else {
            candle_core::bail!("no micro-batch");
        };
        let norm = clip_grad_norm(&mut grads, &vars, self.settings.clip_grad_norm)?;
        self.last_grad_norm = norm;
        if !norm.is_finite() {
            let names: Vec<&String> = self.groups.iter().flat_map(|g| &g.names).collect();
            let mut bad = vec![];
            for (name, var) in names.iter().zip(&vars) {
                if let Some(g) = grads.get(var.as_tensor()) {
                    let sum = g
                        .to_dtype(DType::F64)?
                        .abs()?
                        .sum_all()?
                        .to_scalar::<f64>()?;
                    if !sum.is_finite() {
                        bad.push(name.as_str());
                    }
                }
            }
            candle_core::bail!(
                "gradient norm is {norm} at step {}: non-finite gradient of {} ({} tensor(s)); stopping (the last saved adapter is kept)",
                self.step + 1,
                bad.first().copied().unwrap_or("?"),
                bad.len()
            );
        }
        let s = &self.settings;
        let f = lr_factor(s.schedule, self.step, s.steps, s.warmup);
        for g in &mut self.groups {
            g.update(&grads, g.peak_lr * f, s.weight_decay, self.step + 1)?;
        }
        self.step += 1;
        Ok(total)
    }

    /// What the network output of `batch` looks like where the loss is computed: counts of
    /// non-finite values and of values ≤ 0 (depth under a logarithm) over the valid pixels.
    fn output_diagnosis(&mut self, batch: &[&Sample]) -> String {
        let run = |me: &mut Self| -> Result<String> {
            let mut parts = vec![];
            for (k, s) in batch.iter().enumerate() {
                let (c, h, w) = s.input.dim();
                let x = Tensor::from_vec(
                    s.input.iter().copied().collect::<Vec<f32>>(),
                    (1, c, h, w),
                    me.net.device(),
                )?;
                let y: Vec<f64> = me
                    .net
                    .forward(&x)?
                    .to_dtype(DType::F64)?
                    .flatten_all()?
                    .to_vec1()?;
                let valid = s.valid_pixels(me.settings.min_depth_m, me.settings.max_depth_m);
                let vals = valid.iter().map(|&i| y[i as usize]);
                let non_finite = vals.clone().filter(|v| !v.is_finite()).count();
                let non_positive = vals.filter(|v| *v <= 0.0).count();
                parts.push(format!(
                    "sample {k} of the batch: network output has {non_finite} non-finite and {non_positive} non-positive value(s) over {} valid pixel(s)",
                    valid.len()
                ));
            }
            Ok(parts.join("; "))
        };
        run(self).unwrap_or_else(|e| format!("(output not inspectable: {e})"))
    }

    /// Mean loss over `samples` (one at a time, no dropout, no update).
    ///
    /// # Errors
    /// As [`Trainer::step`].
    pub fn eval_loss<'a>(&mut self, samples: impl IntoIterator<Item = &'a Sample>) -> Result<f64> {
        let (mut sum, mut n) = (0.0, 0usize);
        for s in samples {
            let l = self.batch_loss(&[s])?.detach();
            sum += l.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            n += 1;
        }
        if n == 0 {
            candle_core::bail!("no samples to evaluate");
        }
        Ok(sum / n as f64)
    }

    /// Writes the optimiser state atomically to `path` (safetensors): the AdamW moments of every
    /// trained variable (`exp_avg.NAME`, `exp_avg_sq.NAME`), the trained head weights
    /// (`param.NAME`; LoRA matrices are in the adapter), the step count and `run` (the settings
    /// of the run, JSON; [`Trainer::load_state`] refuses a state made with other settings).
    /// Tensors keep their dtype (f32 or f64), so a resumed run continues bit for bit.
    ///
    /// # Errors
    /// [`crate::DepthError::Weights`] naming the file.
    pub fn save_state(&self, path: &Path, run: &serde_json::Value) -> crate::Result<()> {
        let err = |e: candle_core::Error| aerr(path, e.to_string());
        let mut views = BTreeMap::new();
        for g in &self.groups {
            for (i, name) in g.names.iter().enumerate() {
                views.insert(
                    format!("exp_avg.{name}"),
                    F32View::of(&g.m[i]).map_err(err)?,
                );
                views.insert(
                    format!("exp_avg_sq.{name}"),
                    F32View::of(&g.v[i]).map_err(err)?,
                );
                if g.kind == "head" {
                    views.insert(
                        format!("param.{name}"),
                        F32View::of(g.vars[i].as_tensor()).map_err(err)?,
                    );
                }
            }
        }
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), OPTIM_STATE_FORMAT.to_string());
        meta.insert("step".to_string(), self.step.to_string());
        meta.insert("run".to_string(), run.to_string());
        let bytes = safetensors::tensor::serialize(&views, Some(meta))
            .map_err(|e| aerr(path, e.to_string()))?;
        write_atomic(path, &bytes)
    }

    /// Restores a state written by [`Trainer::save_state`]: moments, trained head weights and
    /// the step count (so the schedule continues where it stopped).
    ///
    /// # Errors
    /// [`crate::DepthError::Weights`] naming the file: unreadable, not a moma optimiser state,
    /// made with settings other than `run` (the differing keys are named), missing, extra or
    /// mis-shaped tensors. Nothing is changed on error.
    pub fn load_state(&mut self, path: &Path, run: &serde_json::Value) -> crate::Result<()> {
        let bytes = std::fs::read(path).map_err(|e| aerr(path, e.to_string()))?;
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
            .map_err(|e| aerr(path, format!("not a safetensors file: {e}")))?;
        let meta = header
            .metadata()
            .clone()
            .ok_or_else(|| aerr(path, "no metadata: not a moma optimiser state"))?;
        if meta.get("format").map(String::as_str) != Some(OPTIM_STATE_FORMAT) {
            return Err(aerr(
                path,
                format!("not a moma optimiser state (format {OPTIM_STATE_FORMAT:?} expected)"),
            ));
        }
        let step: usize = meta
            .get("step")
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| aerr(path, "bad or missing `step` in metadata"))?;
        let stored: serde_json::Value = meta
            .get("run")
            .and_then(|s| serde_json::from_str(s).ok())
            .ok_or_else(|| aerr(path, "bad or missing `run` settings in metadata"))?;
        if &stored != run {
            return Err(aerr(path, settings_difference(&stored, run)));
        }
        let mut tensors: HashMap<String, Tensor> =
            candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)
                .map_err(|e| aerr(path, e.to_string()))?;
        // Everything is read and checked before anything is set.
        let mut updates: Vec<(usize, usize, Tensor, Tensor, Option<Tensor>)> = vec![];
        for (gi, g) in self.groups.iter().enumerate() {
            for (i, name) in g.names.iter().enumerate() {
                let want = g.vars[i].as_tensor();
                let mut take = |key: String| -> crate::Result<Tensor> {
                    let t = tensors
                        .remove(&key)
                        .ok_or_else(|| aerr(path, format!("missing tensor {key}")))?;
                    if t.dims() != want.dims() {
                        return Err(aerr(
                            path,
                            format!("{key}: shape {:?}, expected {:?}", t.dims(), want.dims()),
                        ));
                    }
                    t.to_dtype(want.dtype())
                        .and_then(|t| t.to_device(want.device()))
                        .map_err(|e| aerr(path, e.to_string()))
                };
                let m = take(format!("exp_avg.{name}"))?;
                let v = take(format!("exp_avg_sq.{name}"))?;
                let p = if g.kind == "head" {
                    Some(take(format!("param.{name}"))?)
                } else {
                    None
                };
                updates.push((gi, i, m, v, p));
            }
        }
        if let Some(k) = tensors.keys().min() {
            return Err(aerr(
                path,
                format!("unexpected tensor {k} (a state of another set of trained variables)"),
            ));
        }
        for (gi, i, m, v, p) in updates {
            let g = &mut self.groups[gi];
            if let Some(p) = p {
                g.vars[i].set(&p).map_err(|e| aerr(path, e.to_string()))?;
            }
            g.m[i] = m;
            g.v[i] = v;
        }
        self.step = step;
        Ok(())
    }
}

/// The settings that differ between two JSON values, as `key.sub (state A, this run B)`,
/// descending into objects.
fn differences(path: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            for k in keys {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => differences(&p, u, v, out),
                    (u, v) => {
                        let show = |v: Option<&Value>| v.map_or("-".into(), Value::to_string);
                        out.push(format!("{p} (state {}, this run {})", show(u), show(v)));
                    }
                }
            }
        }
        _ if a != b => out.push(format!("{path} (state {a}, this run {b})")),
        _ => {}
    }
}

/// Why a stored run's settings are not this run's.
fn settings_difference(stored: &serde_json::Value, run: &serde_json::Value) -> String {
    let mut diffs = vec![];
    differences("", stored, run, &mut diffs);
    format!(
        "made with other settings; resume with the settings of the original run: {}",
        diffs.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Gradients `c1`, `c2` of `loss = c1·x + c2·y` (closed form).
    fn linear_grads(c1: &[f64], c2: &[f64]) -> (GradStore, Vec<Var>) {
        let dev = Device::Cpu;
        let x = Var::zeros(c1.len(), DType::F64, &dev).unwrap();
        let y = Var::zeros(c2.len(), DType::F64, &dev).unwrap();
        let t1 = Tensor::new(c1, &dev).unwrap();
        let t2 = Tensor::new(c2, &dev).unwrap();
        let l = ((x.as_tensor() * &t1).unwrap().sum_all().unwrap()
            + (y.as_tensor() * &t2).unwrap().sum_all().unwrap())
        .unwrap();
        (l.backward().unwrap(), vec![x, y])
    }

    fn grad(g: &GradStore, v: &Var) -> Vec<f64> {
        g.get(v.as_tensor()).unwrap().to_vec1().unwrap()
    }

    #[test]
    fn clipping_scales_the_global_norm_to_the_limit() {
        let (c1, c2) = ([3.0, -4.0, 12.0], [0.0, 84.0]);
        // Global norm: √(9 + 16 + 144 + 7056) = √7225 = 85.
        let (mut g, vars) = linear_grads(&c1, &c2);
        let norm = clip_grad_norm(&mut g, &vars, 1.7).unwrap();
        assert!((norm - 85.0).abs() < 1e-12);
        let k = 1.7 / (85.0 + 1e-6);
        for (v, c) in vars.iter().zip([&c1[..], &c2[..]]) {
            for (a, b) in grad(&g, v).iter().zip(c) {
                assert!((a - b * k).abs() < 1e-12, "{a} vs {}", b * k);
            }
        }
        let after = clip_grad_norm(&mut g, &vars, 0.0).unwrap();
        assert!((after - 1.7).abs() < 1e-7, "clipped norm {after}");
        // Below the limit, or clipping off: untouched.
        for limit in [85.5, 0.0] {
            let (mut g, vars) = linear_grads(&c1, &c2);
            assert!((clip_grad_norm(&mut g, &vars, limit).unwrap() - 85.0).abs() < 1e-12);
            assert_eq!(grad(&g, &vars[0]), c1.to_vec());
            assert_eq!(grad(&g, &vars[1]), c2.to_vec());
        }
        // A NaN gradient: reported, nothing scaled.
        let (mut g, vars) = linear_grads(&[f64::NAN, 1.0], &[2.0]);
        assert!(clip_grad_norm(&mut g, &vars, 1.0).unwrap().is_nan());
        assert_eq!(grad(&g, &vars[1]), vec![2.0]);
    }

    #[test]
    fn derived_seeds_differ_by_stream_and_index_and_repeat() {
        let a = derive_seed(1, seed_tag::AUGMENT, 0);
        assert_eq!(a, derive_seed(1, seed_tag::AUGMENT, 0));
        assert_ne!(a, derive_seed(1, seed_tag::AUGMENT, 1));
        assert_ne!(a, derive_seed(1, seed_tag::DROPOUT, 0));
        assert_ne!(a, derive_seed(2, seed_tag::AUGMENT, 0));
        let path = optim_state_path(Path::new("dir/glass.safetensors"));
        assert_eq!(path, Path::new("dir/glass.optim.safetensors"));
    }

    #[test]
    fn schedules_warm_up_then_decay() {
        // Warm-up: 1/4, 2/4, 3/4, 4/4.
        for s in 0..4 {
            let f = lr_factor(Schedule::Poly, s, 20, 4);
            assert!((f - (s + 1) as f64 / 4.0).abs() < 1e-12);
        }
        // Right after the warm-up: the peak; at the end: poly 0, one-cycle 1e-3.
        assert!((lr_factor(Schedule::Poly, 4, 20, 4) - 1.0).abs() < 1e-12);
        assert!((lr_factor(Schedule::OneCycle, 4, 20, 4) - 1.0).abs() < 1e-12);
        assert!(lr_factor(Schedule::Poly, 20, 20, 4).abs() < 1e-12);
        assert!((lr_factor(Schedule::OneCycle, 20, 20, 4) - 1e-3).abs() < 1e-12);
        // Half-way: poly 0.5^0.9, one-cycle ≈ 0.5.
        assert!((lr_factor(Schedule::Poly, 12, 20, 4) - 0.5f64.powf(0.9)).abs() < 1e-12);
        assert!((lr_factor(Schedule::OneCycle, 12, 20, 4) - (1e-3 + 0.999 * 0.5)).abs() < 1e-12);
        assert_eq!("one-cycle".parse::<Schedule>(), Ok(Schedule::OneCycle));
        assert!("step".parse::<Schedule>().is_err());
    }
}
