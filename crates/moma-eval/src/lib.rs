//! # moma-eval — reproducing the paper's evaluation
//!
//! - [`simulate`]: the seeded MDEM simulator of METHOD.md §6 (outputs labelled *simulated*);
//! - [`protocol`]: the evaluation protocol of METHOD.md §4 (one calibration frame, n random
//!   samples, every other frame scored inside its mask, mean ± std over seeds);
//! - [`report`]: paper-style tables as text, Markdown, CSV and JSON;
//! - [`ablate`]: the ablations (samples n with fit time, normalisation, prediction source,
//!   transparent objects), each a table plus a PNG plot;
//! - [`figure`]: the Fig.-6-style comparison figure per frame;
//! - [`scene`] and [`demo`]: a procedural fixed-camera scene and the `moma demo` pipeline;
//! - [`data`]: the moma set layout and prediction folders; [`render`]: colour maps and plots.

pub mod ablate;
pub mod data;
pub mod demo;
pub mod error;
pub mod figure;
pub mod imgproc;
pub mod protocol;
pub mod render;
pub mod report;
pub mod scene;
pub mod simulate;

pub use error::{EvalError, Result};
