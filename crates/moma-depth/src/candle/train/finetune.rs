//! The fine-tuning loop: AdamW on the LoRA matrices (and optionally the DPT head with its own
//! learning rate), a warm-up + one-cycle or poly schedule, gradient accumulation, a NaN/inf stop.
//! Data preparation (moma sets, augmentation) is the caller's.

use std::fmt;
use std::str::FromStr;

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

use super::{LossKind, TrainNet, loss, valid_indices};

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
}

/// A training run in progress.
pub struct Trainer {
    net: TrainNet,
    lora_opt: Option<AdamW>,
    head_opt: Option<AdamW>,
    lora_vars: Vec<Var>,
    head_vars: Vec<Var>,
    settings: OptimSettings,
    step: usize,
}

impl Trainer {
    /// Optimisers over the network's LoRA variables and its trained base (head) variables.
    ///
    /// # Errors
    /// No variable to train.
    pub fn new(net: TrainNet, settings: OptimSettings) -> Result<Self> {
        let lora_vars: Vec<Var> = net.lora_vars().values().cloned().collect();
        let head_vars: Vec<Var> = net.base_vars().values().cloned().collect();
        if lora_vars.is_empty() && head_vars.is_empty() {
            candle_core::bail!("nothing to train: no LoRA adapters and no trained head");
        }
        let params = |lr: f64| ParamsAdamW {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: settings.weight_decay,
        };
        let lora_opt = if lora_vars.is_empty() {
            None
        } else {
            Some(AdamW::new(lora_vars.clone(), params(settings.lr))?)
        };
        let head_opt = if head_vars.is_empty() {
            None
        } else {
            Some(AdamW::new(head_vars.clone(), params(settings.head_lr))?)
        };
        Ok(Self {
            net,
            lora_opt,
            head_opt,
            lora_vars,
            head_vars,
            settings,
            step: 0,
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

    /// Sets the step counter (when resuming).
    pub fn set_steps_done(&mut self, step: usize) {
        self.step = step;
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
            let g: Vec<f32> = s.gt_m.iter().copied().collect();
            let m: Option<Vec<bool>> = s.mask.as_ref().map(|m| m.iter().copied().collect());
            let v = valid_indices(
                &g,
                m.as_deref(),
                self.settings.min_depth_m,
                self.settings.max_depth_m,
            );
            valid.extend(v.into_iter().map(|i| i + (k * h * w) as u32));
            gt.extend(g.into_iter().map(|v| if v.is_finite() { v } else { 0.0 }));
        }
        let dev = self.net.device().clone();
        let x = Tensor::from_vec(x, (batch.len(), c, h, w), &dev)?;
        let gt = Tensor::from_vec(gt, (batch.len(), h, w), &dev)?;
        let y = self.net.forward(&x)?;
        loss(self.settings.loss, &y, &gt, &valid)
    }

    /// One optimiser step over `micro` micro-batches (gradients accumulated, loss averaged);
    /// returns the mean loss. A NaN or infinite loss is an error and leaves the weights as they
    /// were.
    ///
    /// # Errors
    /// Shape errors, no valid pixel, a non-finite loss.
    pub fn step(&mut self, micro: &[Vec<&Sample>]) -> Result<f64> {
        self.net.set_training(true);
        let n = micro.len().max(1) as f64;
        let mut total = 0.0;
        let mut acc: Option<GradStore> = None;
        let vars: Vec<Var> = self
            .lora_vars
            .iter()
            .chain(self.head_vars.iter())
            .cloned()
            .collect();
        for batch in micro {
            let l = (self.batch_loss(batch)? / n)?;
            let v = l.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?;
            if !v.is_finite() {
                self.net.set_training(false);
                candle_core::bail!(
                    "loss is {} at step {}: stopping (the last saved adapter is kept)",
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
        let Some(grads) = acc else {
            candle_core::bail!("no micro-batch");
        };
        let s = &self.settings;
        let f = lr_factor(s.schedule, self.step, s.steps, s.warmup);
        if let Some(o) = &mut self.lora_opt {
            o.set_learning_rate(s.lr * f);
            o.step(&grads)?;
        }
        if let Some(o) = &mut self.head_opt {
            o.set_learning_rate(s.head_lr * f);
            o.step(&grads)?;
        }
        self.step += 1;
        Ok(total)
    }

    /// Mean loss over `samples` (one at a time, no dropout, no update).
    ///
    /// # Errors
    /// As [`Trainer::step`].
    pub fn eval_loss(&mut self, samples: &[Sample]) -> Result<f64> {
        if samples.is_empty() {
            candle_core::bail!("no samples to evaluate");
        }
        let mut sum = 0.0;
        for s in samples {
            let l = self.batch_loss(&[s])?.detach();
            sum += l.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?;
        }
        Ok(sum / samples.len() as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
