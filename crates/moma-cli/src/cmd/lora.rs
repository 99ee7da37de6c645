//! `moma lora`: LoRA adapter utilities (`merge`).

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use moma_depth::candle::DepthAnythingConfig;

use super::common::ModelArgs;

/// LoRA adapter utilities.
#[derive(Debug, Clone, Args)]
pub struct LoraArgs {
    #[command(subcommand)]
    pub command: LoraCommand,
}

/// `moma lora` subcommands.
#[derive(Debug, Clone, Subcommand)]
pub enum LoraCommand {
    /// Merge an adapter into its base weights; write full f32 weights (.safetensors, official
    /// key names) that any runtime loads without --lora.
    ///
    /// Example:
    ///   moma lora merge --weights depth_anything_v2_vits.pth --model vits \
    ///       --lora glass.safetensors -o merged.safetensors
    #[command(verbatim_doc_comment)]
    Merge(MergeArgs),
}

/// `moma lora merge` arguments.
#[derive(Debug, Clone, Args)]
pub struct MergeArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// Output weights file (.safetensors).
    #[arg(short, long, visible_alias = "out", value_name = "FILE")]
    pub output: PathBuf,
}

/// Runs `moma lora`.
///
/// # Errors
/// Missing arguments, unreadable weights or adapter, an adapter for other weights, I/O errors.
pub fn run(args: &LoraArgs) -> Result<()> {
    match &args.command {
        LoraCommand::Merge(a) => {
            let Some(adapter) = &a.model.lora else {
                bail!("lora merge needs --lora ADAPTER");
            };
            // merging rewrites a file in f32 on the CPU: a precision or a runtime asked for
            // would not be what it writes (the device it would run on does not matter)
            let m = &a.model;
            if m.backend == super::common::BackendArg::Onnx
                || m.dtype != super::common::DtypeArg::F32
            {
                bail!(
                    "--backend onnx and --dtype choose how a model runs; lora merge writes f32 \
                     weights for candle (run them with `moma predict --weights MERGED --dtype ...`)"
                );
            }
            let (weights, spec) = m.weights_and_spec()?;
            let weights = &weights;
            if super::common::has_extension(weights, "onnx") {
                bail!(
                    "{}: an ONNX model cannot be merged; give the .safetensors or .pth weights \
                     the adapter was trained on",
                    weights.display()
                );
            }
            if a.output.is_dir() {
                bail!(
                    "the output {} is a folder: give the merged weights' file name",
                    a.output.display()
                );
            }
            for input in [weights, adapter] {
                if moma_io::same_file(input, &a.output) {
                    bail!(
                        "the output {} is an input ({}): it would be overwritten; write the \
                         merged weights to a file of their own",
                        a.output.display(),
                        input.display()
                    );
                }
            }
            let config = DepthAnythingConfig::from_spec(&spec);
            moma_depth::candle::train::write_merged(weights, &config, adapter, &a.output)?;
            eprintln!(
                "wrote {} ({} merged into {})",
                a.output.display(),
                adapter.display(),
                weights.display()
            );
            Ok(())
        }
    }
}
