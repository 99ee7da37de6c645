//! `moma finetune`: LoRA fine-tuning of Depth Anything V2 on moma sets (issue 10).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_depth::candle::train::{
    Adapter, LoraConfig, LoraTarget, LossKind, OptimSettings, ParamSource, Sample, Schedule,
    TrainNet, Trainer, derive_seed, fingerprint, seed_tag,
};
use moma_depth::candle::{DepthAnythingConfig, open_checkpoint, open_device, precision_dtype};
use moma_depth::{Head, preprocess};
use moma_io::MomaSet;
use ndarray::{Array2, Array3, Axis, s};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::common::{ModelArgs, print_json, progress};

/// Fine-tune Depth Anything V2 with LoRA on moma sets; write an adapter (safetensors).
///
/// Trains LoRA adapters on the DINOv2 attention (q and v of attn.qkv by default) with AdamW,
/// warm-up + one-cycle (or poly) schedule, on frames of moma sets (RGB + ground-truth depth;
/// masks restrict the loss with --mask-loss). A seeded split by frame gives a validation set.
/// Use the adapter with `--lora ADAPTER` in predict/calibrate/align/eval, or `moma lora merge`.
///
/// Random-weight models (the tiny test models) learn nothing meaningful: their losses only show
/// that the machinery works.
///
/// Examples:
///   moma finetune --set data/cleargrasp-transparent --weights depth_anything_v2_metric_hypersim_vits.pth --head metric -o glass.lora.safetensors
///   moma finetune --set SET --weights tiny-metric.safetensors --model tiny-metric.json --input-size 112 --steps 40 -o a.safetensors --json
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct FinetuneArgs {
    /// moma sets to train on (frames are split into train/validation by --val-frac).
    #[arg(long = "set", required = true, num_args = 1.., value_name = "SET")]
    pub sets: Vec<PathBuf>,
    #[command(flatten)]
    pub model: ModelArgs,
    /// LoRA rank r.
    #[arg(long, default_value_t = 16, value_name = "R")]
    pub lora_rank: usize,
    /// LoRA alpha (update scale alpha/r) [default: the rank].
    #[arg(long, value_name = "A")]
    pub lora_alpha: Option<f64>,
    /// Adapted layers of every block, comma-separated: q, k, v (parts of attn.qkv), proj
    /// (attn.proj), fc1, fc2 (the MLP).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "q,v",
        value_name = "LIST"
    )]
    pub lora_targets: Vec<LoraTarget>,
    /// Dropout on the adapter input.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub lora_dropout: f32,
    /// Also train the DPT head fully (learning rate --head-lr-mult × --lr).
    #[arg(long)]
    pub train_head: bool,
    /// Head learning rate as a multiple of --lr (the official recipe: 10).
    #[arg(long, default_value_t = 10.0, value_name = "X")]
    pub head_lr_mult: f64,
    /// Loss: silog (official Depth Anything V2), silog-moma (the authors' variant), ssi
    /// (scale-and-shift-invariant in disparity; relative heads) [default: silog for metric heads,
    /// ssi for relative heads].
    #[arg(long, value_name = "LOSS")]
    pub loss: Option<LossKind>,
    /// Optimiser steps.
    #[arg(long, value_name = "N", conflicts_with = "epochs")]
    pub steps: Option<usize>,
    /// Epochs over the training frames (instead of --steps).
    #[arg(long, value_name = "E")]
    pub epochs: Option<usize>,
    /// Frames per micro-batch.
    #[arg(long, default_value_t = 1, value_name = "B")]
    pub batch: usize,
    /// Micro-batches accumulated per optimiser step.
    #[arg(long, default_value_t = 1, value_name = "K")]
    pub accumulate: usize,
    /// Peak learning rate of the adapters.
    #[arg(long, default_value_t = 5e-4, value_name = "LR")]
    pub lr: f64,
    /// AdamW weight decay.
    #[arg(long, default_value_t = 0.01)]
    pub weight_decay: f64,
    /// Learning-rate schedule after the warm-up: one-cycle or poly.
    #[arg(long, default_value = "one-cycle", value_name = "NAME")]
    pub schedule: Schedule,
    /// Warm-up, fraction of the steps (linear).
    #[arg(long, default_value_t = 0.05, value_name = "F")]
    pub warmup_frac: f64,
    /// Fraction of the frames held out for validation (at least one frame when > 0).
    #[arg(long, default_value_t = 0.2, value_name = "F")]
    pub val_frac: f64,
    /// Validation loss every N steps (0: only before and after).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub val_every: usize,
    /// Save the adapter every N steps (0: only at the end).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub save_every: usize,
    /// Ground truth below this depth is invalid, metres.
    #[arg(long, default_value_t = 0.001, value_name = "METRES")]
    pub min_depth: f32,
    /// Restrict the loss to the frames' masks (mask.png).
    #[arg(long)]
    pub mask_loss: bool,
    /// No augmentation (flip, colour jitter); crops stay random.
    #[arg(long)]
    pub no_augment: bool,
    /// Seed of the split, initialisation, crops, augmentation and dropout.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Continue from this adapter and its optimiser state `ADAPTER.optim.safetensors` (written
    /// next to every saved adapter): LoRA matrices, AdamW moments, trained head weights and the
    /// step, so the run continues exactly as if it had not stopped. Every other setting must be
    /// the original run's (a difference is an error that names it).
    #[arg(long, value_name = "ADAPTER")]
    pub resume: Option<PathBuf>,
    /// Stop after N optimiser steps of this invocation (the schedule still spans --steps);
    /// continue later with --resume.
    #[arg(long, value_name = "N")]
    pub stop_after: Option<usize>,
    /// Clip the global L2 norm of the gradients to this value (as PyTorch clip_grad_norm_);
    /// 0 = no clipping.
    #[arg(long, default_value_t = 1.0, value_name = "NORM")]
    pub clip_grad_norm: f64,
    /// Random crop HxW (pixels, multiples of 14, at most the network-size frame) of every
    /// training frame [default: the whole frame, resized as `moma predict` does: the shorter
    /// side to --input-size, aspect kept, both sides multiples of 14].
    #[arg(long, value_name = "HxW", value_parser = parse_crop)]
    pub crop: Option<(usize, usize)>,
    /// Diagnostics: keep the T×T attention probabilities of every block for the backward (the
    /// composed softmax) instead of recomputing them there; more memory, for comparisons.
    #[arg(long, hide = true)]
    pub keep_attention: bool,
    /// Diagnostics: run the operations a GPU runs (candle operations with attached backwards)
    /// on the CPU too, instead of the CPU kernels: to test that path and measure its memory
    /// where no GPU is at hand.
    #[arg(long, hide = true)]
    pub portable_ops: bool,
    /// Output adapter file (.safetensors).
    #[arg(short, long, visible_alias = "out", value_name = "ADAPTER")]
    pub output: PathBuf,
    /// Print one JSON object on stdout (and no progress bar).
    #[arg(long)]
    pub json: bool,
}

/// The `--json` summary.
#[derive(Debug, Serialize)]
struct Summary {
    steps: usize,
    /// Mean training loss over the first 10 % of steps.
    train_loss_first: f64,
    /// Mean training loss over the last 10 % of steps.
    train_loss_last: f64,
    val_loss_before: Option<f64>,
    val_loss_after: Option<f64>,
    adapter: PathBuf,
    /// Median wall time of one optimiser step (its samples' loading and augmentation
    /// included; validation and adapter saves excluded), seconds. The median keeps the first
    /// step's one-off warm-up (allocations, page faults) out of the figure once 3 or more steps
    /// ran.
    step_time_s: f64,
    loss: LossKind,
    train_frames: usize,
    val_frames: usize,
    /// What these numbers are.
    note: &'static str,
}

/// Most frames per micro-batch and most micro-batches per step (`--batch`, `--accumulate`).
const MAX_BATCH: usize = 4096;
/// Most optimiser steps of one run (`--steps`, or `--epochs` turned into steps).
const MAX_STEPS: usize = 100_000_000;

/// `HxW` → (H, W), both positive multiples of 14.
fn parse_crop(s: &str) -> std::result::Result<(usize, usize), String> {
    let bad = || format!("--crop {s:?}: expected HxW in pixels, e.g. 518x686");
    let (h, w) = s.trim().split_once(['x', 'X']).ok_or_else(bad)?;
    let h: usize = h.trim().parse().map_err(|_| bad())?;
    let w: usize = w.trim().parse().map_err(|_| bad())?;
    if h == 0 || w == 0 || !h.is_multiple_of(14) || !w.is_multiple_of(14) {
        return Err(format!(
            "--crop {h}x{w}: both sides must be positive multiples of 14 (the ViT patch size)"
        ));
    }
    Ok((h, w))
}

/// One frame at network resolution (before cropping / augmentation).
struct Frame {
    input: Array3<f32>,
    gt_m: Array2<f32>,
    mask: Option<Array2<bool>>,
}

/// Nearest-neighbour resize (ground truth and masks must not be blended across edges).
fn resize_nearest<T: Copy>(src: &Array2<T>, h: usize, w: usize) -> Array2<T> {
    let (sh, sw) = src.dim();
    Array2::from_shape_fn((h, w), |(y, x)| {
        let sy = ((y as f64 + 0.5) * sh as f64 / h as f64).floor() as usize;
        let sx = ((x as f64 + 0.5) * sw as f64 / w as f64).floor() as usize;
        src[[sy.min(sh - 1), sx.min(sw - 1)]]
    })
}

fn load_frames(
    args: &ModelArgs,
    sets: &[PathBuf],
    mask_loss: bool,
) -> Result<Vec<(String, Frame)>> {
    let mut out = vec![];
    let mut size: Option<(moma_core::ImageSize, String)> = None;
    for root in sets {
        let set =
            MomaSet::open(root).with_context(|| format!("opening moma set {}", root.display()))?;
        if set.frames.is_empty() {
            bail!("moma set {} has no frames", root.display());
        }
        for f in &set.frames {
            let name = format!("{}/frames/{}", root.display(), f.id);
            match &size {
                None => size = Some((f.size, name.clone())),
                Some((s, first)) if *s != f.size => bail!(
                    "frames of mixed sizes: {name} is {}x{}, {first} is {}x{} (fine-tune on one camera's frames)",
                    f.size.width,
                    f.size.height,
                    s.width,
                    s.height
                ),
                Some(_) => {}
            }
            let rgb = f
                .load_rgb()
                .with_context(|| format!("reading {}", f.rgb.display()))?;
            let depth = f
                .load_depth()
                .with_context(|| format!("reading {}", f.depth.display()))?;
            if !depth.depth_m.iter().any(|&d| d.is_finite() && d > 0.0) {
                bail!(
                    "{name}: the ground-truth depth {} has no valid pixel",
                    f.depth.display()
                );
            }
            let input = preprocess::preprocess(&rgb, args.input_size)?;
            let (_, h, w) = input.dim();
            let gt_m = resize_nearest(&depth.depth_m, h, w);
            let mask = if mask_loss {
                let m = f.load_mask_or_full()?;
                Some(resize_nearest(m.data(), h, w))
            } else {
                None
            };
            out.push((name, Frame { input, gt_m, mask }));
        }
    }
    Ok(out)
}

/// A random `crop` (H, W) of the network-size frame (the whole frame when `None`), with a
/// horizontal flip (p = 0.5) and brightness/contrast jitter (±20 %) when `augment`.
fn training_sample(
    f: &Frame,
    crop: Option<(usize, usize)>,
    augment: bool,
    rng: &mut ChaCha8Rng,
) -> Sample {
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
        // Back to [0, 1] RGB, jitter, clamp, re-normalise.
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
                let j =
                    ((f64::from(v) - f64::from(mean)) * contrast + f64::from(mean)) * brightness;
                *d = ((j.clamp(0.0, 1.0) - m) / sd) as f32;
            });
        }
    }
    Sample { input, gt_m, mask }
}

fn eval_sample(f: &Frame) -> Sample {
    Sample {
        input: f.input.clone(),
        gt_m: f.gt_m.clone(),
        mask: f.mask.clone(),
    }
}

/// Runs `moma finetune`.
///
/// # Errors
/// Bad arguments or data, training failure (a non-finite loss stops the run; the last saved
/// adapter is kept).
pub fn run(args: &FinetuneArgs) -> Result<()> {
    let m = &args.model;
    let Some(weights) = &m.weights else {
        bail!("fine-tuning needs --weights FILE (.safetensors or .pth)");
    };
    if m.lora.is_some() {
        bail!("--lora does not apply to finetune (use --resume to continue an adapter)");
    }
    let spec = m.spec()?;
    let config = DepthAnythingConfig::from_spec(&spec);
    let loss_kind = args.loss.unwrap_or(match spec.head {
        Head::Metric { .. } => LossKind::Silog,
        Head::Relative => LossKind::Ssi,
    });
    match (spec.head, loss_kind) {
        (Head::Relative, LossKind::Silog | LossKind::SilogMoma) => {
            bail!(
                "--loss {loss_kind} needs a metric head (a relative head predicts disparity): use --loss ssi"
            )
        }
        (Head::Metric { .. }, LossKind::Ssi) => {
            bail!(
                "--loss ssi is for relative heads (disparity); a metric head trains with silog or silog-moma"
            )
        }
        _ => {}
    }
    let max_depth_m = match spec.head {
        Head::Metric { max_depth_m } => max_depth_m,
        Head::Relative => f32::INFINITY,
    };
    let mut targets = args.lora_targets.clone();
    targets.sort_unstable();
    let lora = LoraConfig {
        rank: args.lora_rank,
        alpha: args.lora_alpha.unwrap_or(args.lora_rank as f64),
        targets,
        dropout: args.lora_dropout,
        seed: args.seed,
    };
    lora.validate(&config).map_err(anyhow::Error::msg)?;
    if args.batch == 0 || args.accumulate == 0 {
        bail!("--batch and --accumulate must be at least 1");
    }
    // Bounds that keep the run's bookkeeping finite (a huge --batch was reserved up front and
    // aborted; batch × accumulate wrapped): far above what fits on any accelerator.
    if args.batch > MAX_BATCH || args.accumulate > MAX_BATCH {
        bail!(
            "--batch {} / --accumulate {}: at most {MAX_BATCH} each",
            args.batch,
            args.accumulate
        );
    }
    if !(0.0..1.0).contains(&args.val_frac) {
        bail!("--val-frac {} must be in [0, 1)", args.val_frac);
    }
    if !(args.lr.is_finite() && args.lr > 0.0) {
        bail!("--lr {} must be positive", args.lr);
    }
    if !(args.clip_grad_norm.is_finite() && args.clip_grad_norm >= 0.0) {
        bail!(
            "--clip-grad-norm {} must be a finite norm ≥ 0 (0 = no clipping)",
            args.clip_grad_norm
        );
    }
    if args.stop_after == Some(0) {
        bail!("--stop-after 0: nothing to do");
    }

    // Data: a seeded split by frame.
    let mut frames = load_frames(m, &args.sets, args.mask_loss)?;
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    frames.shuffle(&mut rng);
    let n_val = if args.val_frac > 0.0 {
        ((frames.len() as f64 * args.val_frac).round() as usize).max(1)
    } else {
        0
    };
    if frames.len() <= n_val {
        bail!(
            "{} frame(s) cannot be split into training and validation (--val-frac {}); add frames or use --val-frac 0",
            frames.len(),
            args.val_frac
        );
    }
    let val: Vec<Sample> = frames[..n_val]
        .iter()
        .map(|(_, f)| eval_sample(f))
        .collect();
    let train: Vec<Frame> = frames
        .split_off(n_val)
        .into_iter()
        .map(|(_, f)| f)
        .collect();
    if let (Some((ch, cw)), Some(f)) = (args.crop, train.first()) {
        let (_, h, w) = f.input.dim();
        if ch > h || cw > w {
            bail!(
                "--crop {ch}x{cw} is larger than the network-size frames ({h}x{w} at --input-size {}); use a smaller crop or a larger --input-size",
                m.input_size
            );
        }
    }
    let per_step = args.batch * args.accumulate;
    let steps = match (args.steps, args.epochs) {
        (Some(s), _) => s,
        (None, Some(e)) => e
            .checked_mul(train.len())
            .with_context(|| format!("--epochs {e} over {} frames overflows", train.len()))?
            .div_ceil(per_step),
        (None, None) => bail!("give --steps N or --epochs E"),
    };
    if steps == 0 {
        bail!("nothing to do: 0 steps");
    }
    if steps > MAX_STEPS {
        bail!("{steps} optimiser steps: at most {MAX_STEPS}");
    }

    // Model.
    let device = open_device(m.device)?;
    let dtype = precision_dtype(moma_depth::Precision::F32, &device)?;
    let base = open_checkpoint(weights, &config, &device, dtype)?;
    let fp = fingerprint(&base, &config)?;
    let train_head = args.train_head;
    let src = ParamSource::new(base, move |name: &str| {
        train_head && name.starts_with("depth_head.")
    });
    let mut net = TrainNet::new(&config, src)?;
    net.set_recompute_attention(!args.keep_attention);
    net.set_portable_ops(args.portable_ops);
    net.add_lora(&lora)?;
    let mut resumed: Option<(PathBuf, u64)> = None;
    if let Some(resume) = &args.resume {
        let a = Adapter::load(resume)?;
        a.check_base(&config, &fp)
            .map_err(|e| anyhow::anyhow!("--resume {}: {e}", resume.display()))?;
        net.set_lora_values(&a)
            .with_context(|| format!("--resume {}", resume.display()))?;
        let Some(done) = a.settings["steps_done"].as_u64() else {
            bail!(
                "--resume {}: the adapter does not record its step (settings.steps_done)",
                resume.display()
            );
        };
        let state = moma_depth::candle::train::optim_state_path(resume);
        if !state.is_file() {
            bail!(
                "--resume {}: no optimiser state {} next to it (moma finetune writes it with every adapter; without it the AdamW moments and the schedule position cannot be restored)",
                resume.display(),
                state.display()
            );
        }
        resumed = Some((state, done));
    }
    let settings = OptimSettings {
        loss: loss_kind,
        lr: args.lr,
        head_lr: args.lr * args.head_lr_mult,
        weight_decay: args.weight_decay,
        steps,
        warmup: ((steps as f64 * args.warmup_frac).ceil() as usize).min(steps),
        schedule: args.schedule,
        accumulate: args.accumulate,
        min_depth_m: args.min_depth,
        max_depth_m,
        clip_grad_norm: args.clip_grad_norm,
    };
    // What a resumed run must share with the run it continues.
    let run_settings = serde_json::json!({
        "base_fingerprint": fp,
        "model": spec,
        "optim": settings,
        "lora": lora,
        "batch": args.batch,
        "seed": args.seed,
        "sets": args.sets,
        "train_head": args.train_head,
        "input_size": m.input_size,
        "crop": args.crop,
        "augment": !args.no_augment,
        "mask_loss": args.mask_loss,
        "val_frac": args.val_frac,
    });
    let mut trainer = Trainer::new(net, settings.clone())?;
    if let Some((state, done)) = &resumed {
        trainer.load_state(state, &run_settings)?;
        if trainer.steps_done() as u64 != *done {
            bail!(
                "--resume: the adapter is at step {done} but its optimiser state {} at step {} (an interrupted save?)",
                state.display(),
                trainer.steps_done()
            );
        }
    }
    let start_step = trainer.steps_done();
    let record = |trainer: &Trainer, done: usize| -> Result<Adapter> {
        Ok(trainer.net().adapter(
            &fp,
            serde_json::json!({
                "weights": weights,
                "model": spec,
                "optim": settings,
                "batch": args.batch,
                "seed": args.seed,
                "sets": args.sets,
                "train_head": args.train_head,
                "steps_done": done,
            }),
        )?)
    };
    // The optimiser state first, the adapter last: a step mismatch reveals an interrupted save.
    let save = |trainer: &Trainer, path: &Path| -> Result<()> {
        let done = trainer.steps_done();
        trainer.save_state(
            &moma_depth::candle::train::optim_state_path(path),
            &run_settings,
        )?;
        record(trainer, done)?.save(path)?;
        Ok(())
    };

    let val_before = if val.is_empty() {
        None
    } else {
        Some(trainer.eval_loss(&val)?)
    };
    let bar = progress(steps, "fine-tuning", args.json);
    let mut losses = Vec::with_capacity(steps.min(1 << 16));
    // Every draw of a step comes from (seed, step) or (seed, epoch): a resumed run draws what
    // the uninterrupted run would have.
    let mut order: (Option<u64>, Vec<usize>) = (None, vec![]);
    let mut step_times_s = Vec::with_capacity(steps.min(1 << 16));
    let end = args
        .stop_after
        .map_or(steps, |k| start_step.saturating_add(k).min(steps));
    for step in start_step..end {
        let t_step = Instant::now();
        let mut rng =
            ChaCha8Rng::seed_from_u64(derive_seed(args.seed, seed_tag::AUGMENT, step as u64));
        let mut micro = Vec::with_capacity(args.accumulate);
        for a in 0..args.accumulate {
            let mut b = Vec::with_capacity(args.batch);
            for k in 0..args.batch {
                let j = ((step * args.accumulate + a) * args.batch + k) as u64;
                let epoch = j / train.len() as u64;
                if order.0 != Some(epoch) {
                    let mut perm: Vec<usize> = (0..train.len()).collect();
                    perm.shuffle(&mut ChaCha8Rng::seed_from_u64(derive_seed(
                        args.seed,
                        seed_tag::ORDER,
                        epoch,
                    )));
                    order = (Some(epoch), perm);
                }
                let i = order.1[(j % train.len() as u64) as usize];
                b.push(training_sample(
                    &train[i],
                    args.crop,
                    !args.no_augment,
                    &mut rng,
                ));
            }
            micro.push(b);
        }
        let refs: Vec<Vec<&Sample>> = micro.iter().map(|b| b.iter().collect()).collect();
        let l = trainer
            .step(&refs)
            .with_context(|| format!("training step {}", step + 1))?;
        step_times_s.push(t_step.elapsed().as_secs_f64());
        losses.push(l);
        bar.set_message(format!(
            "fine-tuning, loss {l:.4} (random-weight models: not meaningful)"
        ));
        bar.inc(1);
        let done = step + 1;
        if args.val_every > 0 && done % args.val_every == 0 && !val.is_empty() && !args.json {
            let v = trainer.eval_loss(&val)?;
            bar.println(format!(
                "step {done}: train loss {l:.5}, validation loss {v:.5}"
            ));
        }
        if args.save_every > 0 && done % args.save_every == 0 && done < end {
            save(&trainer, &args.output)?;
        }
    }
    bar.finish_and_clear();
    let ran = losses.len();
    let step_time_s = median_s(&mut step_times_s);
    save(&trainer, &args.output)?;
    let val_after = if val.is_empty() {
        None
    } else {
        Some(trainer.eval_loss(&val)?)
    };
    let tenth = (ran / 10).max(1);
    let mean = |xs: &[f64]| {
        if xs.is_empty() {
            f64::NAN
        } else {
            xs.iter().sum::<f64>() / xs.len() as f64
        }
    };
    let summary = Summary {
        steps: ran,
        train_loss_first: mean(&losses[..tenth.min(ran)]),
        train_loss_last: mean(&losses[ran.saturating_sub(tenth)..]),
        val_loss_before: val_before,
        val_loss_after: val_after,
        adapter: args.output.clone(),
        step_time_s,
        loss: loss_kind,
        train_frames: train.len(),
        val_frames: val.len(),
        note: "losses of the given weights; with random-weight (test) models they show only that training runs, not depth accuracy",
    };
    if args.json {
        print_json(&summary)?;
    } else {
        eprintln!(
            "{} steps, {:.3} s/step; training loss {:.5} -> {:.5}; validation loss {} -> {}; adapter {}",
            summary.steps,
            step_time_s,
            summary.train_loss_first,
            summary.train_loss_last,
            val_before.map_or("-".into(), |v| format!("{v:.5}")),
            val_after.map_or("-".into(), |v| format!("{v:.5}")),
            args.output.display()
        );
    }
    Ok(())
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
