//! Shared by the CLI tests: run a command that must succeed, read a ground-truth log.
#![allow(dead_code)]

use serde_json::Value;
use std::path::Path;
use std::process::Command;

/// Run `c`; assert it succeeded (printing its stderr otherwise) and return its stderr.
pub fn run_ok(c: &mut Command) -> String {
    let out = c.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{err}");
    err
}

/// Every record of a JSON Lines log.
pub fn records(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The frame records among `recs`.
pub fn frames(recs: &[Value]) -> Vec<&Value> {
    recs.iter().filter(|r| r["record"] == "frame").collect()
}
