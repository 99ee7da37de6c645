//! `moma finetune`: LoRA fine-tuning of Depth Anything V2 on moma sets. The run itself (data
//! pipeline, training, the report) is `moma_train::finetune`; this parses and prints.

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::Args;
use moma_depth::candle::train::{LoraTarget, LossKind, Schedule};
use moma_train::{Event, FinetuneOptions, finetune};

use super::common::{ModelArgs, print_json, progress};

/// Fine-tune Depth Anything V2 with LoRA on moma sets; write an adapter (safetensors).
///
/// Trains LoRA adapters on the DINOv2 attention (q and v of attn.qkv by default) with AdamW,
/// warm-up + one-cycle (or poly) schedule, on frames of moma sets (RGB + ground-truth depth;
/// masks restrict the loss with --mask-loss). A seeded split by frame gives a validation set.
/// Use the adapter with `--lora ADAPTER` in every command that runs the model (predict, calibrate,
/// align, eval, grasp, grasp-eval, ablate, demo, ros2), or `moma lora merge`.
///
/// Random-weight models (the tiny test models) learn nothing meaningful: their losses only show
/// that the machinery works.
///
/// Examples:
///   moma finetune --set data/cleargrasp-transparent \
///       --weights depth_anything_v2_metric_hypersim_vits.pth --head metric -o glass.lora.safetensors
///   moma finetune --set SET --weights tiny-metric.safetensors --model tiny-metric.json \
///       --input-size 112 --steps 40 -o a.safetensors --json
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
    /// Head learning rate as a multiple of --lr. Default 1: the head at the adapters' rate. The
    /// official Depth Anything V2 recipe's 10 applies to a full fine-tune at 5e-6 (head 5e-5);
    /// times a LoRA rate (5e-4 to 1e-3) it gives 5e-3 to 1e-2, where AdamW (whose step is about
    /// the learning rate whatever the gradient's scale) moves the metric head's logits by tens
    /// per step and saturates its sigmoid (docs/depth-model.md, "Fine-tuning that reaches inference", item 1).
    #[arg(long, default_value_t = 1.0, value_name = "X")]
    pub head_lr_mult: f64,
    /// Loss: silog (official Depth Anything V2), silog-moma (the authors' variant), ssi
    /// (scale-and-shift-invariant in disparity; relative heads) [default: silog for metric heads,
    /// ssi for relative heads].
    #[arg(long, value_name = "LOSS")]
    pub loss: Option<LossKind>,
    /// Optimiser steps.
    #[arg(
        long,
        value_name = "N",
        conflicts_with = "epochs",
        required_unless_present = "epochs"
    )]
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

/// `HxW` → (H, W) in pixels (the sizes are checked by `FinetuneOptions`: multiples of 14).
fn parse_crop(s: &str) -> std::result::Result<(usize, usize), String> {
    let bad = || format!("--crop {s:?}: expected HxW in pixels, e.g. 518x686");
    let (h, w) = s.trim().split_once(['x', 'X']).ok_or_else(bad)?;
    let h: usize = h.trim().parse().map_err(|_| bad())?;
    let w: usize = w.trim().parse().map_err(|_| bad())?;
    Ok((h, w))
}

/// Runs `moma finetune`.
///
/// # Errors
/// Bad arguments or data, training failure (a non-finite loss stops the run; the last saved
/// adapter is kept).
pub fn run(args: &FinetuneArgs) -> Result<()> {
    let m = &args.model;
    if m.lora.is_some() {
        bail!("--lora does not apply to finetune (use --resume to continue an adapter)");
    }
    // training runs on the candle backend in f32: options that would choose otherwise are
    // refused rather than ignored (before --hub would fetch a checkpoint)
    if m.dtype != super::common::DtypeArg::F32 {
        bail!(
            "fine-tuning trains in f32: --dtype applies to inference (`moma predict --lora \
             ADAPTER --dtype ...` runs the trained adapter at another precision)"
        );
    }
    let onnx = |weights: Option<&std::path::Path>| {
        m.backend == super::common::BackendArg::Onnx
            || weights.is_some_and(|w| super::common::has_extension(w, "onnx"))
    };
    let refuse_onnx = || {
        anyhow::anyhow!(
            "fine-tuning trains the candle backend's network: --weights must be .safetensors or \
             .pth (an ONNX model cannot be trained), and --backend onnx does not apply"
        )
    };
    // before --hub would fetch a checkpoint, and again for the file it resolved to
    if onnx(m.weights.as_deref()) {
        return Err(refuse_onnx());
    }
    let (weights, spec) = m.weights_and_spec()?;
    if onnx(Some(&weights)) {
        return Err(refuse_onnx());
    }
    let mut opts = FinetuneOptions::new(args.sets.clone(), weights, spec, args.output.clone());
    opts.device = m.device;
    opts.lora_rank = args.lora_rank;
    opts.lora_alpha = args.lora_alpha;
    opts.lora_targets = args.lora_targets.clone();
    opts.lora_dropout = args.lora_dropout;
    opts.train_head = args.train_head;
    opts.head_lr_mult = args.head_lr_mult;
    opts.loss = args.loss;
    opts.steps = args.steps;
    opts.epochs = args.epochs;
    opts.batch = args.batch;
    opts.accumulate = args.accumulate;
    opts.lr = args.lr;
    opts.weight_decay = args.weight_decay;
    opts.schedule = args.schedule;
    opts.warmup_frac = args.warmup_frac;
    opts.val_frac = args.val_frac;
    opts.val_every = args.val_every;
    opts.save_every = args.save_every;
    opts.min_depth_m = args.min_depth;
    opts.mask_loss = args.mask_loss;
    opts.augment = !args.no_augment;
    opts.seed = args.seed;
    opts.resume = args.resume.clone();
    opts.stop_after = args.stop_after;
    opts.clip_grad_norm = args.clip_grad_norm;
    opts.crop = args.crop;
    opts.keep_attention = args.keep_attention;
    opts.portable_ops = args.portable_ops;

    // With --epochs the number of steps is known only once the frames are split: the bar's
    // length is set from the first step's event (2 keeps it visible until then).
    let bar = progress(args.steps.unwrap_or(2), "fine-tuning", args.json);
    let report = finetune(&opts, &mut |event| match event {
        Event::Step { done, total, loss } => {
            if bar.length() != Some(total as u64) {
                bar.set_length(total as u64);
            }
            bar.set_position(done as u64);
            bar.set_message(format!(
                "fine-tuning, loss {loss:.4} (random-weight models: not meaningful)"
            ));
            std::ops::ControlFlow::Continue(())
        }
        Event::Validation { done, loss } => {
            if !args.json {
                let line = format!("step {done}: validation loss {loss:.5}");
                // a hidden bar (stderr not a terminal: a log file, CI) prints nothing
                if bar.is_hidden() {
                    eprintln!("{line}");
                } else {
                    bar.println(line);
                }
            }
            std::ops::ControlFlow::Continue(())
        }
    })?;
    bar.finish_and_clear();
    if args.json {
        print_json(&report)?;
    } else {
        let show = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.5}"));
        eprintln!(
            "{} steps, {:.3} s/step; training loss {:.5} -> {:.5}; validation loss {} -> {} (reloaded adapter: {}); adapter {}",
            report.steps,
            report.step_time_s,
            report.train_loss_first,
            report.train_loss_last,
            show(report.val_loss_before),
            show(report.val_loss_after),
            show(report.val_loss_after_reload),
            report.adapter.display()
        );
        // what the numbers are (the progress bar's reminder is not shown in a log file)
        eprintln!("note: {}", report.note);
    }
    Ok(())
}
