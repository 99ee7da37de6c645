//! One fine-tuning run, from options to a written adapter and a report.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use moma_depth::candle::train::{
    Adapter, LoraConfig, LoraTarget, LossKind, OptimSettings, ParamSource, Sample, Schedule,
    TrainNet, Trainer, derive_seed, fingerprint, loss, optim_state_path, seed_tag,
};
use moma_depth::candle::{DepthAnythingConfig, open_checkpoint, open_device, precision_dtype};
use moma_depth::{
    Backend, DepthModel, DeviceRequest, Head, LoadOptions, LoadSpec, ModelSpec, Precision, load,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::TrainError;
use crate::data::{self, Frame};

/// Most frames per micro-batch and most micro-batches per step (a huge batch was reserved up
/// front and aborted; batch × accumulate wrapped): far above what fits on any accelerator.
pub const MAX_BATCH: usize = 4096;

/// The largest learning rate (and head learning rate) a run takes.
pub const MAX_LR: f64 = 1.0;
/// Most optimiser steps of one run (`steps`, or `epochs` turned into steps).
pub const MAX_STEPS: usize = 100_000_000;

/// Every setting of a run. [`FinetuneOptions::new`] gives `moma finetune`'s defaults.
#[derive(Debug, Clone)]
pub struct FinetuneOptions {
    /// moma sets to train on (their frames are split into training and validation).
    pub sets: Vec<PathBuf>,
    /// Base weights (`.safetensors` or `.pth`, official key names).
    pub weights: PathBuf,
    /// The network (backbone, head, input size).
    pub spec: ModelSpec,
    /// Device of the candle backend.
    pub device: DeviceRequest,
    /// LoRA rank r.
    pub lora_rank: usize,
    /// LoRA alpha (update scale alpha/r); `None` = the rank.
    pub lora_alpha: Option<f64>,
    /// Adapted layers of every block.
    pub lora_targets: Vec<LoraTarget>,
    /// Dropout on the adapters' input.
    pub lora_dropout: f32,
    /// Also train the DPT head fully (learning rate `head_lr_mult × lr`).
    pub train_head: bool,
    /// Head learning rate as a multiple of `lr` (default 1; see `moma finetune --help`).
    pub head_lr_mult: f64,
    /// Loss; `None` = silog for metric heads, ssi for relative heads.
    pub loss: Option<LossKind>,
    /// Optimiser steps (or `epochs`).
    pub steps: Option<usize>,
    /// Epochs over the training frames (when `steps` is `None`).
    pub epochs: Option<usize>,
    /// Frames per micro-batch.
    pub batch: usize,
    /// Micro-batches accumulated per optimiser step.
    pub accumulate: usize,
    /// Peak learning rate of the adapters.
    pub lr: f64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// Schedule after the warm-up.
    pub schedule: Schedule,
    /// Warm-up, fraction of the steps.
    pub warmup_frac: f64,
    /// Fraction of the frames held out for validation.
    pub val_frac: f64,
    /// Validation loss every N steps, reported as [`Event::Validation`] (0: only before/after).
    pub val_every: usize,
    /// Save the adapter every N steps (0: only at the end).
    pub save_every: usize,
    /// Ground truth below this depth is invalid, metres.
    pub min_depth_m: f32,
    /// Restrict the loss to the frames' masks.
    pub mask_loss: bool,
    /// Flips and colour jitter (crops are random either way).
    pub augment: bool,
    /// Seed of the split, initialisation, crops, augmentation and dropout.
    pub seed: u64,
    /// Continue from this adapter and its optimiser state.
    pub resume: Option<PathBuf>,
    /// Stop after N optimiser steps of this call (the schedule still spans `steps`).
    pub stop_after: Option<usize>,
    /// Clip the global gradient L2 norm to this value; 0 = no clipping.
    pub clip_grad_norm: f64,
    /// Random crop (H, W) in pixels, multiples of 14; `None` = the whole frame.
    pub crop: Option<(usize, usize)>,
    /// Diagnostics: keep the attention probabilities for the backward.
    pub keep_attention: bool,
    /// Diagnostics: the portable (GPU) operations on the CPU too.
    pub portable_ops: bool,
    /// The adapter to write (`.safetensors`); its optimiser state goes next to it.
    pub output: PathBuf,
}

impl FinetuneOptions {
    /// `moma finetune`'s defaults for these sets, weights, network and output.
    pub fn new(sets: Vec<PathBuf>, weights: PathBuf, spec: ModelSpec, output: PathBuf) -> Self {
        Self {
            sets,
            weights,
            spec,
            device: DeviceRequest::Auto,
            lora_rank: 16,
            lora_alpha: None,
            lora_targets: LoraTarget::DEFAULT.to_vec(),
            lora_dropout: 0.0,
            train_head: false,
            head_lr_mult: 1.0,
            loss: None,
            steps: None,
            epochs: None,
            batch: 1,
            accumulate: 1,
            lr: 5e-4,
            weight_decay: 0.01,
            schedule: Schedule::OneCycle,
            warmup_frac: 0.05,
            val_frac: 0.2,
            val_every: 0,
            save_every: 0,
            min_depth_m: 0.001,
            mask_loss: false,
            augment: true,
            seed: 0,
            resume: None,
            stop_after: None,
            clip_grad_norm: 1.0,
            crop: None,
            keep_attention: false,
            portable_ops: false,
            output,
        }
    }

    /// The loss this run trains with.
    ///
    /// # Errors
    /// A loss that does not fit the head (silog on disparity, ssi on metres).
    pub fn loss_kind(&self) -> Result<LossKind, TrainError> {
        let kind = self.loss.unwrap_or(match self.spec.head {
            Head::Metric { .. } => LossKind::Silog,
            Head::Relative => LossKind::Ssi,
        });
        match (self.spec.head, kind) {
            (Head::Relative, LossKind::Silog | LossKind::SilogMoma) => Err(TrainError::Invalid(
                format!(
                    "loss {kind} needs a metric head (a relative head predicts disparity): use ssi"
                ),
            )),
            (Head::Metric { .. }, LossKind::Ssi) => Err(TrainError::Invalid(
                "loss ssi is for relative heads (disparity); a metric head trains with silog or silog-moma".into(),
            )),
            _ => Ok(kind),
        }
    }

    /// Checks every bound that does not need the data.
    fn check(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::Invalid(m));
        if self.batch == 0 || self.accumulate == 0 {
            return bad("batch and accumulate must be at least 1".into());
        }
        if self.batch > MAX_BATCH || self.accumulate > MAX_BATCH {
            return bad(format!(
                "batch {} / accumulate {}: at most {MAX_BATCH} each",
                self.batch, self.accumulate
            ));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return bad(format!("learning rate {} must be positive", self.lr));
        }
        if !(self.head_lr_mult.is_finite() && self.head_lr_mult > 0.0) {
            return bad(format!(
                "head learning-rate multiplier {} must be positive",
                self.head_lr_mult
            ));
        }
        // AdamW's steps are about the learning rate in size: beyond 1 every weight moves by
        // more than its own scale at each step (fine-tuning uses 1e-5 to 1e-3)
        if self.lr > MAX_LR || self.lr * self.head_lr_mult > MAX_LR {
            return bad(format!(
                "learning rate {:e} (head {:e}) is above {MAX_LR}: every step would move the weights \
                 by more than their own size",
                self.lr,
                self.lr * self.head_lr_mult
            ));
        }
        // the output is checked before training, not found unwritable after it
        // (resuming in place, `--resume a -o a`, is safe: the adapter is read whole first and
        // saved atomically; the base weights and the sets are what must not be written over)
        if let Some(p) = std::iter::once(&self.weights)
            .chain(&self.sets)
            .find(|p| moma_io::same_file(p, &self.output))
        {
            return bad(format!(
                "the output {} is an input of the run ({}): it would be overwritten",
                self.output.display(),
                p.display()
            ));
        }
        if self.output.is_dir() {
            return bad(format!(
                "the output {} is a folder: give the adapter's file name (e.g. {}/adapter.safetensors)",
                self.output.display(),
                self.output.display()
            ));
        }
        if let Some(parent) = self.output.parent().filter(|p| !p.as_os_str().is_empty())
            && !parent.is_dir()
        {
            return bad(format!(
                "the output's folder {} does not exist",
                parent.display()
            ));
        }
        for (i, a) in self.sets.iter().enumerate() {
            if let Some(b) = self.sets[..i].iter().find(|b| moma_io::same_file(a, b)) {
                return bad(format!(
                    "set {} is given twice ({}): its validation frames would be trained on",
                    a.display(),
                    b.display()
                ));
            }
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return bad(format!("weight decay {} must be ≥ 0", self.weight_decay));
        }
        if !(0.0..=1.0).contains(&self.warmup_frac) {
            return bad(format!(
                "warm-up fraction {} must be in [0, 1]",
                self.warmup_frac
            ));
        }
        if !(self.clip_grad_norm.is_finite() && self.clip_grad_norm >= 0.0) {
            return bad(format!(
                "gradient clipping norm {} must be a finite norm ≥ 0 (0 = no clipping)",
                self.clip_grad_norm
            ));
        }
        if !(self.min_depth_m.is_finite() && self.min_depth_m >= 0.0) {
            return bad(format!(
                "minimum depth {} m must be a finite depth ≥ 0",
                self.min_depth_m
            ));
        }
        if self.stop_after == Some(0) {
            return bad("stop after 0 steps: nothing to do".into());
        }
        if let Some((h, w)) = self.crop
            && (h == 0 || w == 0 || !h.is_multiple_of(14) || !w.is_multiple_of(14))
        {
            return bad(format!(
                "crop {h}x{w}: both sides must be positive multiples of 14 (the ViT patch size)"
            ));
        }
        if self.steps.is_some() && self.epochs.is_some() {
            return bad("give steps or epochs, not both".into());
        }
        Ok(())
    }
}

/// Progress of a run, for a progress bar or a log.
#[derive(Debug, Clone, Copy)]
pub enum Event {
    /// Optimiser step `done` of `total` finished with mean training loss `loss`.
    Step {
        /// Steps done (1-based).
        done: usize,
        /// Steps of the whole schedule.
        total: usize,
        /// Mean loss of the step.
        loss: f64,
    },
    /// The validation loss after step `done` (every `val_every` steps).
    Validation {
        /// Steps done.
        done: usize,
        /// Mean validation loss.
        loss: f64,
    },
}

/// What a run reports (`moma finetune --json`, `moma.finetune`).
#[derive(Debug, Clone, Serialize)]
pub struct FinetuneReport {
    /// Optimiser steps run by this call.
    pub steps: usize,
    /// Mean training loss over the first 10 % of the steps.
    pub train_loss_first: f64,
    /// Mean training loss over the last 10 % of the steps.
    pub train_loss_last: f64,
    /// Validation loss of the starting weights (the base, or the resumed adapter).
    pub val_loss_before: Option<f64>,
    /// Validation loss of the trained network, as the trainer computes it.
    pub val_loss_after: Option<f64>,
    /// Validation loss recomputed from the written adapter, loaded through the inference path
    /// (`moma predict --lora`): equal to `val_loss_after` up to the two networks' f32 round-off.
    pub val_loss_after_reload: Option<f64>,
    /// The adapter written.
    pub adapter: PathBuf,
    /// Median wall time of one optimiser step (its samples' loading and augmentation included;
    /// validation and saves excluded), seconds.
    pub step_time_s: f64,
    /// The loss trained with.
    pub loss: LossKind,
    /// Frames trained on.
    pub train_frames: usize,
    /// Frames held out.
    pub val_frames: usize,
    /// Every `val_every` validation of the run, in step order (empty without `val_every`).
    pub validations: Vec<Validation>,
    /// What these numbers are.
    pub note: &'static str,
}

/// One validation during a run ([`FinetuneReport::validations`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Validation {
    /// Optimiser steps done (counted over the whole run, resumed ones included).
    pub step: usize,
    /// Validation loss then.
    pub loss: f64,
}

/// The mean loss of `model` (the inference network, e.g. loaded with an adapter) over whole
/// `frames`, computed from its raw network output with the trainer's loss.
///
/// # Errors
/// Network or shape errors; a frame without a valid ground-truth pixel; for the log losses, a
/// depth ≤ 0 or not finite at a valid pixel (the metric head's sigmoid underflows to 0 in f32
/// below logits of about −104: the log loss is undefined there), naming the frame.
pub fn validation_loss_of_model(
    model: &mut dyn DepthModel,
    frames: &[Frame],
    kind: LossKind,
    min_depth_m: f32,
    max_depth_m: f32,
) -> Result<f64, TrainError> {
    if frames.is_empty() {
        return Err(TrainError::Data("no frames to evaluate".into()));
    }
    let mut sum = 0.0;
    for f in frames {
        let s = &f.sample;
        let out = model.forward_net(&s.input)?;
        if out.dim() != s.gt_m.dim() {
            return Err(TrainError::Data(format!(
                "{}: network output {:?} and ground truth {:?} differ in size",
                f.name,
                out.dim(),
                s.gt_m.dim()
            )));
        }
        let valid = s.valid_pixels(min_depth_m, max_depth_m);
        let pred: Vec<f32> = out.iter().copied().collect();
        let needs_positive = matches!(kind, LossKind::Silog | LossKind::SilogMoma);
        let bad = valid
            .iter()
            .map(|&i| pred[i as usize])
            .filter(|&p| !p.is_finite() || (needs_positive && p <= 0.0))
            .count();
        if bad > 0 {
            return Err(TrainError::Data(format!(
                "{}: the model's output is not finite{} at {bad} of {} valid pixel(s): the {kind} loss is undefined there",
                f.name,
                if needs_positive { " or ≤ 0" } else { "" },
                valid.len()
            )));
        }
        let dims = out.dim();
        let l = Tensor::from_vec(pred, dims, &Device::Cpu)
            .and_then(|p| {
                let g = Tensor::from_vec(s.loss_target(), dims, &Device::Cpu)?;
                loss(kind, &p, &g, &valid)
            })
            .and_then(|l| l.to_dtype(DType::F64)?.to_scalar::<f64>())
            .map_err(TrainError::training(format!(
                "{}: loss of the model's output",
                f.name
            )))?;
        sum += l;
    }
    Ok(sum / frames.len() as f64)
}

/// Runs a fine-tuning: loads and splits the data, trains, writes the adapter (and its optimiser
/// state, for `resume`), and reports; `on_event` sees every step and stops the run by returning
/// `ControlFlow::Break` (Python's Ctrl-C).
///
/// # Errors
/// Bad options or data, unreadable weights, a resume that does not match, a non-finite loss or
/// gradient (the message names the step, the frames and the tensor; the last saved adapter is
/// kept), [`TrainError::Interrupted`] when `on_event` stops it.
pub fn finetune(
    opts: &FinetuneOptions,
    on_event: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<FinetuneReport, TrainError> {
    opts.check()?;
    let spec = opts.spec;
    moma_depth::preprocess::check_input_size(spec.input_size)
        .map_err(|e| TrainError::Invalid(format!("input size: {e}")))?;
    let config = DepthAnythingConfig::from_spec(&spec);
    let loss_kind = opts.loss_kind()?;
    let max_depth_m = match spec.head {
        Head::Metric { max_depth_m } => max_depth_m,
        Head::Relative => f32::INFINITY,
    };
    let mut targets = opts.lora_targets.clone();
    targets.sort_unstable();
    let lora = LoraConfig {
        rank: opts.lora_rank,
        alpha: opts.lora_alpha.unwrap_or(opts.lora_rank as f64),
        targets,
        dropout: opts.lora_dropout,
        seed: opts.seed,
    };
    lora.validate(&config).map_err(TrainError::Invalid)?;

    // Data: a seeded split by frame.
    let frames = data::load_frames(&opts.sets, spec.input_size, opts.mask_loss)?;
    let (train, val) = data::split(frames, opts.val_frac, opts.seed)?;
    if let (Some((ch, cw)), Some(f)) = (opts.crop, train.first()) {
        let (_, h, w) = f.sample.input.dim();
        if ch > h || cw > w {
            return Err(TrainError::Invalid(format!(
                "crop {ch}x{cw} is larger than the network-size frames ({h}x{w} at input size {}); use a smaller crop or a larger input size",
                spec.input_size
            )));
        }
    }
    let per_step = opts.batch * opts.accumulate;
    let steps = match (opts.steps, opts.epochs) {
        (Some(s), _) => s,
        (None, Some(e)) => e
            .checked_mul(train.len())
            .ok_or_else(|| {
                TrainError::Invalid(format!("{e} epochs over {} frames overflows", train.len()))
            })?
            .div_ceil(per_step),
        (None, None) => return Err(TrainError::Invalid("give steps or epochs".into())),
    };
    if steps == 0 {
        return Err(TrainError::Invalid("nothing to do: 0 steps".into()));
    }
    if steps > MAX_STEPS {
        return Err(TrainError::Invalid(format!(
            "{steps} optimiser steps: at most {MAX_STEPS}"
        )));
    }

    // Model.
    let device = open_device(opts.device)?;
    let dtype = precision_dtype(Precision::F32, &device)?;
    let base = open_checkpoint(&opts.weights, &config, &device, dtype)?;
    let fp = fingerprint(&base, &config)?;
    let train_head = opts.train_head;
    let src = ParamSource::new(base, move |name: &str| {
        train_head && name.starts_with("depth_head.")
    });
    let building = TrainError::training("building the training network");
    let mut net = TrainNet::new(&config, src).map_err(building)?;
    net.set_recompute_attention(!opts.keep_attention);
    net.set_portable_ops(opts.portable_ops);
    net.add_lora(&lora)
        .map_err(TrainError::training("adding the LoRA adapters"))?;
    let mut resumed: Option<(PathBuf, u64)> = None;
    if let Some(resume) = &opts.resume {
        let a = Adapter::load(resume)?;
        let ctx = |e: String| TrainError::Invalid(format!("resume {}: {e}", resume.display()));
        a.check_base(&config, &fp).map_err(ctx)?;
        net.set_lora_values(&a)
            .map_err(TrainError::training(format!("resume {}", resume.display())))?;
        let Some(done) = a.settings["steps_done"].as_u64() else {
            return Err(ctx(
                "the adapter does not record its step (settings.steps_done)".into(),
            ));
        };
        let state = optim_state_path(resume);
        if !state.is_file() {
            return Err(ctx(format!(
                "no optimiser state {} next to it (moma finetune writes it with every adapter; without it the AdamW moments and the schedule position cannot be restored)",
                state.display()
            )));
        }
        resumed = Some((state, done));
    }
    let settings = OptimSettings {
        loss: loss_kind,
        lr: opts.lr,
        head_lr: opts.lr * opts.head_lr_mult,
        weight_decay: opts.weight_decay,
        steps,
        warmup: ((steps as f64 * opts.warmup_frac).ceil() as usize).min(steps),
        schedule: opts.schedule,
        accumulate: opts.accumulate,
        min_depth_m: opts.min_depth_m,
        max_depth_m,
        clip_grad_norm: opts.clip_grad_norm,
    };
    // What a resumed run must share with the run it continues.
    let run_settings = serde_json::json!({
        "base_fingerprint": fp,
        "model": spec,
        "optim": settings,
        "lora": lora,
        "batch": opts.batch,
        "seed": opts.seed,
        "sets": opts.sets,
        "train_head": opts.train_head,
        "input_size": spec.input_size,
        "crop": opts.crop,
        "augment": opts.augment,
        "mask_loss": opts.mask_loss,
        "val_frac": opts.val_frac,
    });
    let mut trainer = Trainer::new(net, settings.clone())
        .map_err(TrainError::training("starting the optimiser"))?;
    if let Some((state, done)) = &resumed {
        trainer.load_state(state, &run_settings)?;
        if trainer.steps_done() as u64 != *done {
            return Err(TrainError::Invalid(format!(
                "resume: the adapter is at step {done} but its optimiser state {} at step {} (an interrupted save?)",
                state.display(),
                trainer.steps_done()
            )));
        }
    }
    let start_step = trainer.steps_done();
    let record = |trainer: &Trainer, done: usize| -> Result<Adapter, TrainError> {
        trainer
            .net()
            .adapter(
                &fp,
                serde_json::json!({
                    "weights": opts.weights,
                    "model": spec,
                    "optim": settings,
                    "batch": opts.batch,
                    "seed": opts.seed,
                    "sets": opts.sets,
                    "train_head": opts.train_head,
                    "steps_done": done,
                }),
            )
            .map_err(TrainError::training("collecting the adapter"))
    };
    // The optimiser state first, the adapter last: a step mismatch reveals an interrupted save.
    let save = |trainer: &Trainer, path: &Path| -> Result<(), TrainError> {
        let done = trainer.steps_done();
        trainer.save_state(&optim_state_path(path), &run_settings)?;
        record(trainer, done)?.save(path)?;
        Ok(())
    };
    let validate = |trainer: &mut Trainer, what: &str| -> Result<Option<f64>, TrainError> {
        if val.is_empty() {
            return Ok(None);
        }
        trainer
            .eval_loss(val.iter().map(|f| &f.sample))
            .map(Some)
            .map_err(TrainError::training(format!("validation loss {what}")))
    };

    let val_before = validate(&mut trainer, "before training")?;
    let mut losses = Vec::with_capacity(steps.min(1 << 16));
    let mut validations = Vec::new();
    // Every draw of a step comes from (seed, step) or (seed, epoch): a resumed run draws what
    // the uninterrupted run would have.
    let mut order: (Option<u64>, Vec<usize>) = (None, vec![]);
    let mut step_times_s = Vec::with_capacity(steps.min(1 << 16));
    let end = opts
        .stop_after
        .map_or(steps, |k| start_step.saturating_add(k).min(steps));
    for step in start_step..end {
        let t_step = Instant::now();
        let mut rng =
            ChaCha8Rng::seed_from_u64(derive_seed(opts.seed, seed_tag::AUGMENT, step as u64));
        let mut micro = Vec::with_capacity(opts.accumulate);
        let mut names = Vec::with_capacity(per_step);
        for a in 0..opts.accumulate {
            let mut b = Vec::with_capacity(opts.batch);
            for k in 0..opts.batch {
                let j = ((step * opts.accumulate + a) * opts.batch + k) as u64;
                let i = data::frame_at(j, train.len(), opts.seed, &mut order);
                names.push(train[i].name.as_str());
                b.push(data::training_sample(
                    &train[i],
                    opts.crop,
                    opts.augment,
                    &mut rng,
                ));
            }
            micro.push(b);
        }
        let refs: Vec<Vec<&Sample>> = micro.iter().map(|b| b.iter().collect()).collect();
        let l = trainer.step(&refs).map_err(TrainError::training(format!(
            "training step {} (frames {})",
            step + 1,
            names.join(", ")
        )))?;
        step_times_s.push(t_step.elapsed().as_secs_f64());
        losses.push(l);
        let done = step + 1;
        let mut go_on = on_event(Event::Step {
            done,
            total: steps,
            loss: l,
        });
        if go_on.is_continue()
            && opts.val_every > 0
            && done % opts.val_every == 0
            && let Some(v) = validate(&mut trainer, &format!("after step {done}"))?
        {
            validations.push(Validation {
                step: done,
                loss: v,
            });
            go_on = on_event(Event::Validation { done, loss: v });
        }
        if go_on.is_break() {
            return Err(TrainError::Interrupted { done });
        }
        if opts.save_every > 0 && done % opts.save_every == 0 && done < end {
            save(&trainer, &opts.output)?;
        }
    }
    let ran = losses.len();
    let step_time_s = median_s(&mut step_times_s);
    save(&trainer, &opts.output)?;
    let val_after = validate(&mut trainer, "after training")?;
    // The written adapter, reloaded as every `--lora` consumer loads it.
    let val_after_reload = if val.is_empty() {
        None
    } else {
        let mut model = load(&LoadSpec {
            weights: opts.weights.clone(),
            model: spec,
            options: LoadOptions {
                backend: Backend::Candle,
                device: opts.device,
                precision: Precision::F32,
            },
            adapter: Some(opts.output.clone()),
        })?;
        Some(validation_loss_of_model(
            model.as_mut(),
            &val,
            loss_kind,
            opts.min_depth_m,
            max_depth_m,
        )?)
    };
    let tenth = (ran / 10).max(1);
    let mean = |xs: &[f64]| {
        if xs.is_empty() {
            f64::NAN
        } else {
            xs.iter().sum::<f64>() / xs.len() as f64
        }
    };
    Ok(FinetuneReport {
        steps: ran,
        train_loss_first: mean(&losses[..tenth.min(ran)]),
        train_loss_last: mean(&losses[ran.saturating_sub(tenth)..]),
        val_loss_before: val_before,
        val_loss_after: val_after,
        val_loss_after_reload: val_after_reload,
        adapter: opts.output.clone(),
        step_time_s,
        loss: loss_kind,
        train_frames: train.len(),
        val_frames: val.len(),
        validations,
        note: "losses of the given weights; with random-weight (test) models they show only that training runs, not depth accuracy",
    })
}

/// Median of wall times in seconds (0 for none).
fn median_s(times_s: &mut [f64]) -> f64 {
    if times_s.is_empty() {
        return 0.0;
    }
    times_s.sort_by(f64::total_cmp);
    let n = times_s.len();
    if n % 2 == 1 {
        times_s[n / 2]
    } else {
        0.5 * (times_s[n / 2 - 1] + times_s[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::median_s;

    #[test]
    fn median_of_step_times() {
        assert_eq!(median_s(&mut []), 0.0);
        assert_eq!(median_s(&mut [9.0, 1.0, 2.0]), 2.0);
        assert_eq!(median_s(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
    }
}
