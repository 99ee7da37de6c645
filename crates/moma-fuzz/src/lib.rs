//! # moma-fuzz — fuzzing MOMA's parsers on stable Rust
//!
//! A seeded byte mutator ([`mutate::Mutator`]: bit flips, byte sets, inserts, deletes, splices
//! between seeds, interesting integers, header-field rewrites of decimal numbers, truncation;
//! for JSON documents also structure-aware edits that keep them JSON, [`mutate::Mutator::mutate_json`];
//! PNG chunk CRCs repaired so mutations reach the decoder) over seed corpora ([`seeds`]: small
//! files written by moma-io's writers, plus real files from `$MOMA_SHARED_DIR` read at run time).
//!
//! Each input runs under [`std::panic::catch_unwind`] on a worker thread watched by the calling
//! thread: a panic is a finding, an input that used [`HANG_LIMIT`] of CPU time (or ran for
//! [`HANG_WALL_LIMIT`]) is a hang finding,
//! and (with [`CountingAlloc`] installed as the global allocator, as the `moma-fuzz` binary does)
//! an input that requests one allocation over [`ALLOC_LIMIT_BYTES`] is a memory finding. Each
//! finding is saved as `OUT/TARGET/KIND-seedS-iterI.bin` with a `.txt` description; the input is
//! a pure function of `(seed, target, iteration)`, so `--replay` reproduces it.
//!
//! An abort (e.g. an allocation the machine cannot satisfy) ends the process; rerun with the same
//! `--seed` to reproduce it.

pub mod mutate;
pub mod seeds;
pub mod targets;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::mutate::{Mutator, fix_png_crcs};
use crate::seeds::Corpus;
use crate::targets::Target;

/// An input that has used this much CPU time is a hang finding (on Linux, where the watchdog
/// reads the worker thread's CPU clock; elsewhere this much wall-clock time).
pub const HANG_LIMIT: Duration = Duration::from_secs(1);

/// An input still running after this much wall-clock time is a hang finding whatever CPU time
/// it used (blocked or sleeping). Longer than [`HANG_LIMIT`] so that a loaded machine, where an
/// input waits for a core, does not produce false hangs.
pub const HANG_WALL_LIMIT: Duration = Duration::from_secs(10);

/// A CPU clock of one thread, readable from other threads (Linux).
#[derive(Clone, Copy)]
struct ThreadClock(#[cfg(target_os = "linux")] libc::clockid_t);

impl ThreadClock {
    /// The CPU clock of the calling thread, if the platform has one.
    fn current() -> Option<Self> {
        #[cfg(target_os = "linux")]
        {
            let mut id: libc::clockid_t = 0;
            // SAFETY: `pthread_self` is the calling thread; `id` is a valid out-pointer.
            let rc = unsafe { libc::pthread_getcpuclockid(libc::pthread_self(), &mut id) };
            (rc == 0).then_some(Self(id))
        }
        #[cfg(not(target_os = "linux"))]
        {
            None
        }
    }

    /// CPU time of the thread, nanoseconds.
    fn nanos(self) -> Option<u64> {
        #[cfg(target_os = "linux")]
        {
            let mut t = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: `t` is a valid out-pointer; a clock id of an exited thread gives an error.
            let rc = unsafe { libc::clock_gettime(self.0, &mut t) };
            (rc == 0).then(|| t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64)
        }
        #[cfg(not(target_os = "linux"))]
        {
            None
        }
    }
}

/// One allocation larger than this while parsing one input is a memory finding: the decoders'
/// limits ([`moma_io::MAX_IMAGE_PIXELS`] at 8 bytes per pixel = 512 MiB) keep every legitimate
/// allocation below it.
pub const ALLOC_LIMIT_BYTES: usize = 1 << 30;

thread_local! {
    // Const-initialised and without destructor: safe to touch from inside the allocator.
    static LARGEST_ALLOC: Cell<usize> = const { Cell::new(0) };
}

fn record(size: usize) {
    let _ = LARGEST_ALLOC.try_with(|c| c.set(c.get().max(size)));
}

/// The system allocator, recording per thread the largest single allocation since
/// [`reset_largest_alloc`] (work a parser hands to other threads is not counted).
/// Install it with `#[global_allocator]` to detect inputs that make a parser allocate what a
/// header claims.
pub struct CountingAlloc;

// SAFETY: forwards every call to `System` unchanged; only records sizes.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: the caller upholds `GlobalAlloc::alloc`'s contract.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: as `alloc`.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` was allocated by `System` with `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        // SAFETY: as `GlobalAlloc::realloc`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Forgets the largest allocation this thread recorded so far.
pub fn reset_largest_alloc() {
    LARGEST_ALLOC.with(|c| c.set(0));
}

/// The largest single allocation of this thread since [`reset_largest_alloc`], bytes (0 without
/// [`CountingAlloc`]).
pub fn largest_alloc() -> usize {
    LARGEST_ALLOC.with(Cell::get)
}

/// What went wrong with one input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FindingKind {
    /// The parser panicked.
    Panic,
    /// The parser ran longer than [`HANG_LIMIT`].
    Hang,
    /// The parser asked for one allocation over [`ALLOC_LIMIT_BYTES`].
    Memory,
}

/// One finding.
#[derive(Debug, Clone, Serialize)]
pub struct Finding {
    /// Kind.
    pub kind: FindingKind,
    /// Iteration of the input (with the seed, it reproduces the input).
    pub iteration: u64,
    /// The panic message, the time, or the allocation size.
    pub message: String,
    /// Where the input was saved.
    pub saved: Option<PathBuf>,
}

/// The outcome of fuzzing one target.
#[derive(Debug, Clone, Serialize)]
pub struct TargetReport {
    /// Target name.
    pub target: &'static str,
    /// Seeds in its corpus (generated, shared).
    pub seeds: (usize, usize),
    /// Inputs run (seeds included).
    pub inputs: u64,
    /// Inputs the parser accepted (the rest were refused with an error).
    pub accepted: u64,
    /// Wall-clock time spent, seconds.
    pub seconds: f64,
    /// Findings.
    pub findings: Vec<Finding>,
}

/// A parser on one input: `Ok` accepted, `Err(message)` refused; a panic is a finding.
pub type Parser = Arc<dyn Fn(&[u8]) -> Result<(), String> + Send + Sync>;

/// A parser under test, as the runner sees it.
#[derive(Clone)]
pub struct Harness {
    /// Name (folder of its findings).
    pub name: &'static str,
    /// Index mixed into the mutator's seed, so targets get different inputs.
    pub index: u64,
    /// Whether inputs are PNG files (chunk CRCs are repaired after mutation, most of the time).
    pub png: bool,
    /// Whether inputs are JSON documents (half the inputs get structure-aware edits that keep
    /// them JSON, [`Mutator::mutate_json`], instead of byte mutations).
    pub json: bool,
    /// The parser: `Ok` accepted, `Err(message)` refused; a panic is a finding.
    pub parse: Parser,
}

impl Harness {
    /// The harness of one of moma's targets.
    pub fn of(target: Target) -> Self {
        Self {
            name: target.name(),
            index: Target::ALL.iter().position(|&t| t == target).unwrap_or(0) as u64,
            png: target.is_png(),
            json: target.is_json(),
            parse: Arc::new(move |data| target.run(data)),
        }
    }
}

/// The input of iteration `i` (`i < corpus.len()`: the seeds themselves, unchanged).
pub fn input(harness: &Harness, corpus: &Corpus, seed: u64, iteration: u64) -> Vec<u8> {
    let all: Vec<&[u8]> = corpus.all().map(|s| s.data.as_slice()).collect();
    if all.is_empty() {
        return vec![];
    }
    if let Some(s) = usize::try_from(iteration).ok().and_then(|i| all.get(i)) {
        return s.to_vec();
    }
    let mut m = Mutator::for_input(seed, harness.index, iteration);
    // Generated seeds are small and fast: pick them three times out of four when there are
    // shared ones.
    let n_gen = corpus.generated.len();
    let pick = if n_gen > 0 && (corpus.shared.is_empty() || m.chance(0.75)) {
        m.below(n_gen)
    } else {
        n_gen + m.below(corpus.shared.len())
    };
    let mut data = all[pick].to_vec();
    if !(harness.json && m.chance(0.5) && m.mutate_json(&mut data)) {
        m.mutate(&mut data, &all);
    }
    if harness.png && m.chance(0.8) {
        fix_png_crcs(&mut data);
    }
    data
}

/// Runs `harness` on one input under `catch_unwind`: `Ok(accepted)` or `Err(panic message)`.
///
/// # Errors
/// The panic message when the parser panicked.
pub fn run_one(harness: &Harness, data: &[u8]) -> Result<bool, String> {
    std::panic::catch_unwind(AssertUnwindSafe(|| (harness.parse)(data).is_ok())).map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| (*s).to_string()))
            .unwrap_or_else(|| "panic with a non-string payload".into())
    })
}

fn save_finding(
    out: &Path,
    name: &str,
    seed: u64,
    iteration: u64,
    kind: FindingKind,
    message: &str,
    data: &[u8],
) -> Option<PathBuf> {
    let dir = out.join(name);
    std::fs::create_dir_all(&dir).ok()?;
    let stem = format!("{kind:?}-seed{seed}-iter{iteration}").to_lowercase();
    let bin = dir.join(format!("{stem}.bin"));
    std::fs::write(&bin, data).ok()?;
    let text = format!(
        "target: {}\nkind: {kind:?}\nseed: {seed}\niteration: {iteration}\nmessage: {message}\n\
         replay: moma-fuzz --target {} --replay {}\n",
        name,
        name,
        bin.display()
    );
    std::fs::write(dir.join(format!("{stem}.txt")), text).ok()?;
    Some(bin)
}

/// Fuzzes `target` for `duration` starting at iteration 0 with `seed`, saving findings under
/// `out`. Stops early at a hang (the stuck worker thread cannot be stopped; it is left behind).
///
/// # Errors
/// The worker thread cannot be started.
pub fn fuzz_target(
    harness: &Harness,
    corpus: Arc<Corpus>,
    seed: u64,
    duration: Duration,
    out: &Path,
) -> std::io::Result<TargetReport> {
    let started = Instant::now();
    let iteration = Arc::new(AtomicU64::new(0));
    // Milliseconds since `started` at which the current input began; u64::MAX between inputs.
    let input_started_ms = Arc::new(AtomicU64::new(u64::MAX));
    let stop = Arc::new(AtomicBool::new(false));
    // The worker's CPU clock and its reading when the current input began.
    let (clock_tx, clock_rx) = std::sync::mpsc::channel::<Option<ThreadClock>>();
    let input_started_cpu_ns = Arc::new(AtomicU64::new(0));
    let (tx, rx) = std::sync::mpsc::channel::<Finding>();
    let worker = {
        let (corpus, iteration, input_started_ms, input_started_cpu_ns, stop) = (
            Arc::clone(&corpus),
            Arc::clone(&iteration),
            Arc::clone(&input_started_ms),
            Arc::clone(&input_started_cpu_ns),
            Arc::clone(&stop),
        );
        let out = out.to_path_buf();
        let harness = harness.clone();
        std::thread::Builder::new()
            .name(WORKER_THREAD.into())
            .spawn(move || {
            let clock = ThreadClock::current();
            let _ = clock_tx.send(clock);
            let mut accepted = 0u64;
            while !stop.load(Ordering::Relaxed) {
                let i = iteration.load(Ordering::Relaxed);
                let data = input(&harness, &corpus, seed, i);
                reset_largest_alloc();
                if let Some(ns) = clock.and_then(ThreadClock::nanos) {
                    input_started_cpu_ns.store(ns, Ordering::Relaxed);
                }
                input_started_ms.store(started.elapsed().as_millis() as u64, Ordering::Relaxed);
                let result = run_one(&harness, &data);
                input_started_ms.store(u64::MAX, Ordering::Relaxed);
                let biggest = largest_alloc();
                let finding = match result {
                    Ok(ok) => {
                        accepted += u64::from(ok);
                        (biggest > ALLOC_LIMIT_BYTES).then(|| {
                            (
                                FindingKind::Memory,
                                format!("one allocation of {biggest} bytes (limit {ALLOC_LIMIT_BYTES})"),
                            )
                        })
                    }
                    Err(msg) => Some((FindingKind::Panic, msg)),
                };
                if let Some((kind, message)) = finding {
                    let saved = save_finding(&out, harness.name, seed, i, kind, &message, &data);
                    let _ = tx.send(Finding {
                        kind,
                        iteration: i,
                        message,
                        saved,
                    });
                }
                iteration.store(i + 1, Ordering::Relaxed);
            }
            accepted
        })?
    };
    let worker_clock = clock_rx.recv().ok().flatten();
    let mut findings = vec![];
    let mut hung = false;
    loop {
        std::thread::sleep(Duration::from_millis(20));
        findings.extend(rx.try_iter());
        let now_ms = started.elapsed().as_millis() as u64;
        let began = input_started_ms.load(Ordering::Relaxed);
        let wall_ms = now_ms.saturating_sub(began);
        let hang = if began == u64::MAX || wall_ms <= HANG_LIMIT.as_millis() as u64 {
            None
        } else if wall_ms > HANG_WALL_LIMIT.as_millis() as u64 {
            Some(format!("input still running after {wall_ms} ms"))
        } else {
            let cpu_ms = worker_clock.and_then(ThreadClock::nanos).map(|ns| {
                ns.saturating_sub(input_started_cpu_ns.load(Ordering::Relaxed)) / 1_000_000
            });
            match cpu_ms {
                Some(cpu) if cpu > HANG_LIMIT.as_millis() as u64 => Some(format!(
                    "input still running after {cpu} ms of CPU time ({wall_ms} ms wall-clock)"
                )),
                Some(_) => None,
                None => Some(format!("input still running after {wall_ms} ms")),
            }
        };
        if let Some(message) = hang {
            let i = iteration.load(Ordering::Relaxed);
            let data = input(harness, &corpus, seed, i);
            let saved = save_finding(
                out,
                harness.name,
                seed,
                i,
                FindingKind::Hang,
                &message,
                &data,
            );
            findings.push(Finding {
                kind: FindingKind::Hang,
                iteration: i,
                message,
                saved,
            });
            hung = true;
            break;
        }
        if started.elapsed() >= duration {
            break;
        }
    }
    stop.store(true, Ordering::Relaxed);
    let mut accepted = 0;
    if !hung {
        // The worker finishes its current input (under HANG_LIMIT) and stops.
        accepted = worker.join().unwrap_or(0);
        findings.extend(rx.try_iter());
    }
    Ok(TargetReport {
        target: harness.name,
        seeds: (corpus.generated.len(), corpus.shared.len()),
        inputs: iteration.load(Ordering::Relaxed),
        accepted,
        seconds: started.elapsed().as_secs_f64(),
        findings,
    })
}

/// Name of the threads that run inputs.
const WORKER_THREAD: &str = "moma-fuzz-worker";

/// Silences panic messages on the fuzzing worker threads (their panics are collected as
/// findings); panics elsewhere are reported by the previous hook as usual.
pub fn quiet_panics() {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if std::thread::current().name() != Some(WORKER_THREAD) {
            previous(info);
        }
    }));
}
