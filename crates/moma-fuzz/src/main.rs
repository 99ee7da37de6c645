//! `moma-fuzz`: runs the fuzz targets of [`moma_fuzz`] for a given time; exits non-zero on any
//! finding (panic, hang, oversized allocation).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Parser;
use moma_fuzz::targets::Target;
use moma_fuzz::{CountingAlloc, Harness, TargetReport, fuzz_target, quiet_panics, run_one, seeds};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

/// Fuzz MOMA's parsers (depth PNG16, npy, PFM, masks, RGB, camera.json, calibration JSON,
/// safetensors headers), and calibration files past parsing (aligned and re-aligned with), with a
/// seeded byte mutator. Seeds: small files generated in code, plus
/// the real files under $MOMA_SHARED_DIR (data/ and reference/dav2/) when it is set.
#[derive(Debug, Parser)]
#[command(name = "moma-fuzz", version)]
struct Args {
    /// Target name, or `all`. Targets: depth-png, npy, pfm, mask, rgb, camera-json,
    /// calibration-json, calibration-apply, safetensors-header.
    #[arg(long, default_value = "all")]
    target: String,
    /// Seconds per target.
    #[arg(long, conflicts_with = "total_seconds")]
    seconds: Option<f64>,
    /// Seconds for all selected targets together, shared equally (default: 5 per target).
    #[arg(long)]
    total_seconds: Option<f64>,
    /// Seed of the mutator (inputs are a function of seed, target and iteration).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Folder for findings (OUT/TARGET/KIND-seedS-iterI.bin and .txt).
    #[arg(long, default_value = "fuzz-findings")]
    out: PathBuf,
    /// Print the reports as JSON instead of a table.
    #[arg(long)]
    json: bool,
    /// Run one saved input through `--target` (not `all`) and report what happens.
    #[arg(long)]
    replay: Option<PathBuf>,
    /// Do not read seeds from $MOMA_SHARED_DIR even when it is set.
    #[arg(long)]
    no_shared: bool,
}

fn main() -> ExitCode {
    match run(&Args::parse()) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn run(args: &Args) -> anyhow::Result<bool> {
    let targets: Vec<Target> = if args.target == "all" {
        Target::ALL.to_vec()
    } else {
        vec![Target::from_name(&args.target).with_context(|| {
            let names: Vec<_> = Target::ALL.iter().map(|t| t.name()).collect();
            format!(
                "unknown target '{}' (expected all or one of {})",
                args.target,
                names.join(", ")
            )
        })?]
    };
    if let Some(path) = &args.replay {
        let [target] = targets[..] else {
            bail!("--replay needs one --target");
        };
        let data =
            std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
        return Ok(match run_one(&Harness::of(target), &data) {
            Ok(accepted) => {
                println!(
                    "{}: no panic (input {})",
                    target.name(),
                    if accepted { "accepted" } else { "refused" }
                );
                if let Err(e) = target.run(&data) {
                    println!("  {e}");
                }
                true
            }
            Err(msg) => {
                println!("{}: PANIC: {msg}", target.name());
                false
            }
        });
    }
    let per_target = match (args.seconds, args.total_seconds) {
        (Some(s), _) => s,
        (None, Some(t)) => t / targets.len() as f64,
        (None, None) => 5.0,
    };
    if !(per_target.is_finite() && per_target > 0.0) {
        bail!("the time per target must be positive, got {per_target} s");
    }
    let shared = if args.no_shared {
        None
    } else {
        std::env::var_os("MOMA_SHARED_DIR").map(PathBuf::from)
    };
    quiet_panics();
    let mut reports: Vec<TargetReport> = vec![];
    if !args.json {
        println!(
            "{:<20} {:>6} {:>10} {:>10} {:>8} {:>9}",
            "target", "seeds", "inputs", "accepted", "seconds", "findings"
        );
    }
    for target in targets {
        let corpus = Arc::new(seeds::corpus(target, shared.as_deref())?);
        let report = fuzz_target(
            &Harness::of(target),
            corpus,
            args.seed,
            Duration::from_secs_f64(per_target),
            &args.out,
        )?;
        if !args.json {
            println!(
                "{:<20} {:>6} {:>10} {:>10} {:>8.1} {:>9}",
                report.target,
                format!("{}+{}", report.seeds.0, report.seeds.1),
                report.inputs,
                report.accepted,
                report.seconds,
                report.findings.len()
            );
            for f in &report.findings {
                let saved = f
                    .saved
                    .as_ref()
                    .map(|p| p.display().to_string())
                    .unwrap_or_else(|| "not saved".into());
                println!(
                    "  {:?} at iteration {}: {} ({saved})",
                    f.kind, f.iteration, f.message
                );
            }
        }
        let hung = report
            .findings
            .iter()
            .any(|f| f.kind == moma_fuzz::FindingKind::Hang);
        reports.push(report);
        if hung {
            eprintln!("a hang leaves a stuck thread behind: stopping here");
            break;
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    }
    let findings: usize = reports.iter().map(|r| r.findings.len()).sum();
    if findings > 0 {
        eprintln!("{findings} finding(s) saved under {}", args.out.display());
    }
    Ok(findings == 0)
}
