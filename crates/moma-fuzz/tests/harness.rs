//! The harness finds what it claims to find: panics, hangs and oversized allocations are
//! reported and saved, and inputs are reproducible from (seed, iteration).

use std::sync::Arc;
use std::time::Duration;

use moma_fuzz::seeds::{Corpus, Seed};
use moma_fuzz::{CountingAlloc, FindingKind, Harness, fuzz_target, input, run_one};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

const SEED: &[u8] = b"Pf\n2 1\n-1.0\n\0\0\0\0\0\0\0\0";

fn corpus() -> Arc<Corpus> {
    Arc::new(Corpus {
        generated: vec![Seed {
            origin: "test".into(),
            data: SEED.to_vec(),
        }],
        shared: vec![],
    })
}

fn harness(name: &'static str, parse: fn(&[u8]) -> Result<(), String>) -> Harness {
    Harness {
        name,
        index: 0,
        png: false,
        json: false,
        parse: Arc::new(parse),
    }
}

#[test]
fn panics_are_caught_saved_and_reproducible() {
    moma_fuzz::quiet_panics();
    let out = tempfile::tempdir().unwrap();
    // Panics on any input that differs from the seed (all but the first, almost always).
    let h = harness("panicky", |d| {
        assert_eq!(d, SEED, "mutated");
        Ok(())
    });
    let report = fuzz_target(&h, corpus(), 5, Duration::from_millis(300), out.path()).unwrap();
    assert!(report.inputs > 10, "{report:?}");
    let f = &report.findings[0];
    assert_eq!(f.kind, FindingKind::Panic);
    assert!(f.message.contains("mutated"), "{}", f.message);
    let saved = f.saved.as_ref().expect("saved");
    assert!(saved.starts_with(out.path().join("panicky")));
    assert!(saved.to_string_lossy().contains("seed5"));
    // The saved input is the input of (seed, iteration), and it panics again.
    let data = std::fs::read(saved).unwrap();
    assert_eq!(data, input(&h, &corpus(), 5, f.iteration));
    assert!(run_one(&h, &data).is_err());
    // The seed itself (iteration 0) is run unchanged and does not panic.
    assert_eq!(run_one(&h, &input(&h, &corpus(), 5, 0)), Ok(true));
}

#[test]
fn a_slow_input_is_a_hang_finding() {
    let out = tempfile::tempdir().unwrap();
    // Spins for 12 s: the watchdog reports it after 1 s of CPU time, or at the latest after
    // 10 s of wall-clock time on a machine too loaded to give it that.
    let h = harness("slow", |d| {
        if d != SEED {
            let t = std::time::Instant::now();
            while t.elapsed() < Duration::from_secs(12) {
                std::hint::spin_loop();
            }
        }
        Ok(())
    });
    let report = fuzz_target(&h, corpus(), 1, Duration::from_secs(30), out.path()).unwrap();
    assert_eq!(report.findings.len(), 1, "{report:?}");
    assert_eq!(report.findings[0].kind, FindingKind::Hang);
    // Stopped at the hang, long before the 30 s.
    assert!(report.seconds < 11.0, "{report:?}");
}

#[test]
fn an_oversized_allocation_is_a_memory_finding() {
    let out = tempfile::tempdir().unwrap();
    // Reserves (without touching) 2 GiB, as a decoder trusting a header would.
    let h = harness("greedy", |d| {
        if d != SEED {
            let v: Vec<u8> = Vec::with_capacity(2 << 30);
            std::hint::black_box(&v);
        }
        Ok(())
    });
    let report = fuzz_target(&h, corpus(), 2, Duration::from_millis(200), out.path()).unwrap();
    assert!(!report.findings.is_empty(), "{report:?}");
    assert!(
        report
            .findings
            .iter()
            .all(|f| f.kind == FindingKind::Memory)
    );
    assert!(report.findings[0].message.contains("2147483648 bytes"));
}

#[test]
fn every_target_runs_clean_briefly() {
    // A smoke run of every target on the generated seeds (CI runs the longer one with the
    // shared data: see the crate docs).
    moma_fuzz::quiet_panics();
    let out = tempfile::tempdir().unwrap();
    for target in moma_fuzz::targets::Target::ALL {
        let corpus = Arc::new(moma_fuzz::seeds::corpus(target, None).unwrap());
        assert!(!corpus.is_empty(), "{}", target.name());
        let report = fuzz_target(
            &Harness::of(target),
            corpus,
            0,
            Duration::from_millis(300),
            out.path(),
        )
        .unwrap();
        assert!(report.inputs > 0, "{report:?}");
        assert!(report.findings.is_empty(), "{report:?}");
        // Every seed is a valid file of its kind but for the deliberately odd ones.
        assert!(report.accepted > 0, "{report:?}");
    }
}

#[test]
fn every_generated_calibration_seed_parses_and_applies() {
    // The seeds cover every method, the robust fits, few-shot calibration and anchor stores; a
    // seed the target refuses would leave those fields unfuzzed.
    use moma_fuzz::targets::Target;
    for target in [Target::Calibration, Target::CalibrationApply] {
        let corpus = moma_fuzz::seeds::corpus(target, None).unwrap();
        let names: Vec<&str> = corpus.generated.iter().map(|s| s.origin.as_str()).collect();
        for want in [
            "ssra-local",
            "gssa-local",
            "auto",
            "lwlr-exact",
            "huber",
            "3-frames",
            "anchors",
        ] {
            assert!(names.iter().any(|n| n.contains(want)), "{want}: {names:?}");
        }
        for seed in &corpus.generated {
            assert_eq!(
                target.run(&seed.data),
                Ok(()),
                "{} on {}",
                target.name(),
                seed.origin
            );
        }
    }
}
