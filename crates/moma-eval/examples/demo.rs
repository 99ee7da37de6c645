//! The `moma demo` pipeline without the CLI: `cargo run --release -p moma-eval --example demo [OUT]`.

use std::time::Instant;

use moma_eval::demo::{DemoScene, build_demo, write_visuals};
use moma_eval::protocol::{EvalConfig, evaluate};
use moma_eval::report::{eval_table, write_eval_outputs};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::path::PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "moma-demo".into()),
    );
    let t0 = Instant::now();
    let (set, preds) = build_demo(&DemoScene::default(), Some(&out))?;
    let t_build = t0.elapsed().as_secs_f64();
    let config = EvalConfig::default();
    let results = evaluate(&set, &preds, &config)?;
    let t_eval = t0.elapsed().as_secs_f64() - t_build;
    println!("{}", eval_table(&results, false).to_text());
    write_eval_outputs(&out, "results", &results)?;
    let files = write_visuals(&set, &preds, &config, &out, true)?;
    println!(
        "scene + predictions {t_build:.2} s, evaluation {t_eval:.2} s, total {:.2} s; {} figures, {} point clouds -> {}",
        t0.elapsed().as_secs_f64(),
        files.figures.len(),
        files.point_clouds.len(),
        out.display()
    );
    Ok(())
}
