//! # moma-eval — reproducing the paper's evaluation
//!
//! - [`simulate`]: the seeded MDEM simulator of docs/method.md §6 (outputs labelled *simulated*);
//! - [`protocol`]: the evaluation protocol of docs/method.md §4 (one calibration frame, n random
//!   samples, every other frame scored inside its mask, mean ± std over seeds);
//! - [`report`]: paper-style tables as text, Markdown, CSV and JSON;
//! - [`ablate`]: the ablations (samples n with fit time, normalisation, prediction source,
//!   transparent objects), each a table plus a PNG plot;
//! - [`figure`]: the Fig.-6-style comparison figure per frame;
//! - [`scene`] and [`demo`]: a procedural fixed-camera scene and the `moma demo` pipeline;
//! - [`data`]: the moma set layout and prediction folders; [`render`]: colour maps and plots.

//!
//! ```
//! use moma_eval::demo::{DemoScene, build_demo};
//! use moma_eval::protocol::{EvalConfig, evaluate};
//! use moma_eval::scene::DemoSceneConfig;
//! use moma_core::ImageSize;
//! use moma_core::align::Method;
//!
//! // a small version of the `moma demo` scene, simulated predictions, 2 seeds
//! let demo = DemoScene {
//!     scene: DemoSceneConfig { size: ImageSize::new(160, 120), focal_px: 150.0, frames: 3, ..Default::default() },
//!     ..Default::default()
//! };
//! let (set, preds) = build_demo(&demo, None)?;
//! let methods = vec![Method::Ssra(Default::default()), Method::Gssa];
//! let config = EvalConfig { methods, seeds: 2, ..Default::default() };
//! let results = evaluate(&set, &preds, &config)?;
//! assert_eq!(results.len(), 2);
//! assert!(results[0].per_image.mae.mean < 0.05); // metres
//! println!("{}", moma_eval::report::eval_table(&results, false).to_text());
//! # Ok::<(), moma_eval::EvalError>(())
//! ```

pub mod ablate;
pub mod data;
pub mod demo;
pub mod error;
pub mod figure;
pub mod grasp_eval;
pub mod imgproc;
pub mod protocol;
pub mod realign;
pub mod render;
pub mod report;
pub mod scene;
pub mod simulate;

pub use error::{EvalError, Result};
