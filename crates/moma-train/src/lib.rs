//! LoRA fine-tuning of Depth Anything V2 on moma sets: what `moma finetune` and Python's
//! `moma.finetune` run, so that both take the same options and report the same numbers.
//!
//! [`data`] holds the pipeline (frames at network resolution, a seeded split, crops, flips,
//! colour jitter); [`finetune`] runs a whole training: AdamW on the LoRA matrices (and the head
//! with [`FinetuneOptions::train_head`]), saves and resumes, and measures the validation loss
//! before, after, and once more from the written adapter reloaded through the inference path
//! ([`FinetuneReport::val_loss_after_reload`]): what the trainer reports must hold for what users
//! load.
//!
//! Random-weight models (the tiny test configurations) learn nothing meaningful: their losses
//! show only that training runs.
//!
//! ```no_run
//! use moma_train::{FinetuneOptions, finetune};
//! # fn main() -> Result<(), moma_train::TrainError> {
//! let spec = moma_depth::ModelSpec {
//!     backbone: moma_depth::Backbone::Vits,
//!     head: moma_depth::Head::Metric { max_depth_m: 20.0 },
//!     input_size: 518,
//! };
//! let mut opts = FinetuneOptions::new(vec!["SET".into()], "w.safetensors".into(), spec, "a.safetensors".into());
//! opts.steps = Some(100);
//! let report = finetune(&opts, &mut |_event| std::ops::ControlFlow::Continue(()))?;
//! println!("{:?} -> {:?}", report.val_loss_before, report.val_loss_after_reload);
//! # Ok(()) }
//! ```

pub mod data;
mod run;

pub use run::{
    Event, FinetuneOptions, FinetuneReport, Validation, finetune, validation_loss_of_model,
};

/// What can go wrong in a fine-tuning run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// An option out of range or options that contradict each other.
    #[error("{0}")]
    Invalid(String),
    /// The training data cannot be used (empty set, mixed sizes, no valid ground truth).
    #[error("{0}")]
    Data(String),
    /// A file of a set could not be read.
    #[error(transparent)]
    Io(#[from] moma_io::IoError),
    /// Weights, adapters or the network (boxed: the error type stays small).
    #[error(transparent)]
    Depth(Box<moma_depth::DepthError>),
    /// Training failed; `context` says where (the step and its frames). The cause is the
    /// source only (the CLI and Python print the chain: in the text too it came out twice).
    #[error("{context}")]
    Training {
        /// Where: e.g. "training step 11 (frames SET/frames/a)".
        context: String,
        /// candle's error (a non-finite loss or gradient names the tensor).
        #[source]
        source: Box<candle_core::Error>,
    },
    /// The caller stopped the run (its event callback returned `Break`, e.g. on Ctrl-C) after
    /// `done` steps; the adapter last saved (`save_every`) is kept, nothing else is written.
    #[error(
        "interrupted after step {done}: this run wrote no adapter but those of `save_every`, \
         from which a run can resume"
    )]
    Interrupted {
        /// Steps done when it stopped.
        done: usize,
    },
}

impl From<moma_depth::DepthError> for TrainError {
    fn from(e: moma_depth::DepthError) -> Self {
        Self::Depth(Box::new(e))
    }
}

impl TrainError {
    pub(crate) fn training(context: impl Into<String>) -> impl FnOnce(candle_core::Error) -> Self {
        let context = context.into();
        move |source| Self::Training {
            context,
            source: Box::new(source),
        }
    }
}
