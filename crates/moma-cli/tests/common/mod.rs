//! Helpers shared by the CLI tests: run the `moma` binary and check how it ended.
#![allow(dead_code)] // each test file uses its own subset

use std::path::Path;
use std::process::{Command, Output};

/// Runs `moma ARGS`.
pub fn moma(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moma"))
        .args(args)
        .output()
        .expect("the moma binary runs")
}

/// Runs `moma ARGS`, asserts success, returns stdout.
pub fn ok(args: &[&str]) -> String {
    let out = moma(args);
    assert!(
        out.status.success(),
        "moma {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 stdout")
}

/// Runs `moma ARGS`, asserts failure, returns stderr.
pub fn fails(args: &[&str]) -> String {
    let out = moma(args);
    assert!(!out.status.success(), "moma {args:?} should fail");
    String::from_utf8(out.stderr).expect("utf-8 stderr")
}

/// A path as `&str` for an argument list.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}
