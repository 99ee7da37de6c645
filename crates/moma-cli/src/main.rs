//! `moma`: monocular one-shot metric-depth alignment from the command line.
//!
//! Calibrate once from one RGB-D frame, then turn every RGB-only frame of the same fixed camera
//! into metric depth. Each subcommand lives in its own module under `cmd/`; this file only parses
//! and dispatches.

mod cmd;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// Metric depth from one RGB camera: calibrate once from one RGB-D frame, align every later frame.
#[derive(Debug, Parser)]
#[command(
    name = "moma",
    version,
    about,
    after_help = "Start with `moma demo` (no data needed), then see `moma <command> --help`.\n\
Depth maps: uint16 PNG in millimetres (0 = no depth), float32 .npy in metres, or PFM."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// `about` (not a doc comment) on each variant: a doc comment would also reset the long help
// that each command's `Args` struct documents, and `moma <command> --help` would lose it.
#[derive(Debug, Subcommand)]
enum Command {
    #[command(
        about = "Fit an alignment from one frame's prediction and ground-truth depth; write calib.json."
    )]
    Calibrate(cmd::calibrate::CalibrateArgs),
    #[command(
        about = "Apply a calibration to predictions (or RGB images): metric depth, colour maps, point clouds."
    )]
    Align(cmd::align::AlignArgs),
    #[command(
        about = "Depth metrics (δ1.05, δ1.10, δ1.25, REL, RMSE, MAE) of a metric depth map against ground truth."
    )]
    Metrics(cmd::metrics::MetricsArgs),
    #[command(about = "Run Depth Anything V2 on RGB images and write the raw predictions.")]
    Predict(cmd::predict::PredictArgs),
    #[command(
        about = "Write simulated depth-model predictions for a moma set (labelled \"simulated\")."
    )]
    Simulate(cmd::simulate::SimulateArgs),
    #[command(
        about = "Evaluate alignment methods on moma sets (calibrate on one frame, score all others)."
    )]
    Eval(cmd::eval::EvalArgs),
    #[command(
        about = "Ablations: number of samples, normalisation, prediction source, transparent objects."
    )]
    Ablate(cmd::ablate::AblateArgs),
    #[command(
        about = "Plan parallel-jaw or suction grasps on one frame's metric depth (or calibrated prediction / RGB)."
    )]
    Grasp(cmd::grasp::GraspArgs),
    #[command(
        about = "Grasp success rates by PROXY: plan on aligned depth, execute on ground truth (docs/method.md §8)."
    )]
    GraspEval(cmd::grasp_eval::GraspEvalArgs),
    #[command(
        about = "The whole idea in one command on a bundled procedural scene (or on a real set)."
    )]
    Demo(cmd::demo::DemoArgs),
    #[command(
        about = "Run as a ROS 2 node: RGB (or predictions) in; metric depth, point cloud, grasps out; live calibration."
    )]
    Ros2(Box<cmd::ros2::Ros2Args>),
    #[command(
        about = "Publish a moma set (or a folder of images) as a ROS 2 camera: image, camera_info, depth_sensor, prediction."
    )]
    Ros2Replay(cmd::ros2_replay::Ros2ReplayArgs),
    #[command(about = "Fine-tune Depth Anything V2 with LoRA on moma sets; write an adapter.")]
    #[cfg(feature = "candle")]
    Finetune(cmd::finetune::FinetuneArgs),
    #[command(about = "LoRA adapter utilities (merge into full weights).")]
    #[cfg(feature = "candle")]
    Lora(cmd::lora::LoraArgs),
}

/// The command line with negative numbers taken as values in every subcommand: without it
/// `--min-success-prob -0.1` reads `-0` as an unknown flag, and the error names the wrong
/// problem. With it the value reaches its own check, which says what is out of range.
fn command() -> clap::Command {
    fn negative_numbers_as_values(c: clap::Command) -> clap::Command {
        c.allow_negative_numbers(true)
            .mut_subcommands(negative_numbers_as_values)
    }
    negative_numbers_as_values(Cli::command())
}

/// A closed stdout (`moma calibrate … | head -1`) ends the program quietly, as it ends any Unix
/// filter: Rust ignores SIGPIPE, and `println!` then panicked on the broken pipe. Not for the
/// ROS 2 node and replay, which run for hours on sockets: a broken connection there stays an
/// error to handle, never a signal that ends the node.
fn end_quietly_on_a_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: restores SIGPIPE's default disposition before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// What SIGINT (Ctrl-C), SIGTERM and SIGHUP do ([`handle_signals`]).
#[derive(Clone, Copy, PartialEq)]
enum OnSignal {
    /// A command: remove the temporary files of the outputs being written, then end by the
    /// signal as before.
    RemoveTemporariesAndEnd,
    /// The ROS 2 node and replay: the first signal asks the loop to stop
    /// ([`cmd::common::stop_requested`]), so that the node leaves the DDS domain (its readers
    /// and writers unmatched at once, not after a lease of tens of seconds) and ends with 0; a
    /// second one ends it as [`OnSignal::RemoveTemporariesAndEnd`] does.
    StopGracefully,
}

/// Handles SIGINT, SIGTERM and SIGHUP as `on` says: the signals are blocked in every thread
/// (the mask is inherited, so this runs before any thread starts) and one thread waits for
/// them. A signal the parent left ignored (`nohup`, a script's `cmd &`, `trap '' TERM`) stays
/// ignored: blocked, it would be queued and caught.
fn handle_signals(on: OnSignal) {
    #[cfg(unix)]
    // SAFETY: plain libc calls on a signal set this function owns; run before any other
    // thread exists, so every later thread inherits the blocked mask.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        let mut any = false;
        for signal in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
            let mut current: libc::sigaction = std::mem::zeroed();
            if libc::sigaction(signal, std::ptr::null(), &mut current) != 0
                || current.sa_sigaction == libc::SIG_IGN
            {
                continue;
            }
            libc::sigaddset(&mut set, signal);
            any = true;
        }
        if !any || libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut()) != 0 {
            return;
        }
        let waiter = std::thread::Builder::new()
            .name("moma-signals".into())
            .spawn(move || {
                let mut signal: libc::c_int = 0;
                if libc::sigwait(&set, &mut signal) != 0 {
                    return;
                }
                if on == OnSignal::StopGracefully {
                    cmd::common::request_stop(signal);
                    if libc::sigwait(&set, &mut signal) != 0 {
                        return;
                    }
                }
                // the registry stays locked: no writer finishes another temporary file
                let _held = moma_io::remove_temporaries_in_flight();
                libc::signal(signal, libc::SIG_DFL);
                let mut only: libc::sigset_t = std::mem::zeroed();
                libc::sigemptyset(&mut only);
                libc::sigaddset(&mut only, signal);
                libc::pthread_sigmask(libc::SIG_UNBLOCK, &only, std::ptr::null_mut());
                libc::raise(signal);
                // not reached: the default action of these signals ends the process
                libc::_exit(128 + signal);
            });
        if waiter.is_err() {
            // no thread to wait for them: the signals keep their default action
            libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut());
        }
    }
}

fn main() -> std::process::ExitCode {
    let cli = Cli::from_arg_matches(&command().get_matches()).unwrap_or_else(|e| e.exit());
    if matches!(cli.command, Command::Ros2(_) | Command::Ros2Replay(_)) {
        handle_signals(OnSignal::StopGracefully);
    } else {
        end_quietly_on_a_closed_pipe();
        handle_signals(OnSignal::RemoveTemporariesAndEnd);
    }
    let result = match &cli.command {
        Command::Calibrate(args) => cmd::calibrate::run(args),
        Command::Align(args) => cmd::align::run(args),
        Command::Metrics(args) => cmd::metrics::run(args),
        Command::Predict(args) => cmd::predict::run(args),
        Command::Simulate(args) => cmd::simulate::run(args),
        Command::Eval(args) => cmd::eval::run(args),
        Command::Ablate(args) => cmd::ablate::run(args),
        Command::Grasp(args) => cmd::grasp::run(args),
        Command::GraspEval(args) => cmd::grasp_eval::run(args),
        Command::Demo(args) => cmd::demo::run(args),
        Command::Ros2(args) => cmd::ros2::run(args),
        Command::Ros2Replay(args) => cmd::ros2_replay::run(args),
        #[cfg(feature = "candle")]
        Command::Finetune(args) => cmd::finetune::run(args),
        #[cfg(feature = "candle")]
        Command::Lora(args) => cmd::lora::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {}", error_chain(&err));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The error and its causes joined by ": ". Every library error names only its own context and
/// keeps its cause as `source()`, so each part appears once.
fn error_chain(err: &anyhow::Error) -> String {
    err.chain()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join(": ")
}
