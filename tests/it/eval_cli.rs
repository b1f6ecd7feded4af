//! `scone eval`'s ratio-test flags: a threshold outside (0, 1] is refused while the arguments are parsed, with
//! the flag named, before any scene or model is read.

use std::process::Command;

/// Runs `scone eval ARGS` and returns (succeeded, stderr).
fn eval(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_scone")).arg("eval").args(args).output().unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn a_ratio_outside_zero_to_one_is_refused_naming_its_flag() {
    let cases: [(&[&str], &str); 6] = [
        (&["pairs", "--scene", "/nonexistent", "--ratio", "1.5"], "--ratio"),
        (&["pairs", "--scene", "/nonexistent", "--ratio", "NaN"], "--ratio"),
        (&["pairs", "--scene", "/nonexistent", "--scone-ratio", "0"], "--scone-ratio"),
        (&["homography", "--data", "/nonexistent", "--ratio=-0.8"], "--ratio"),
        (&["homography", "--data", "/nonexistent", "--scone-ratio", "1.01"], "--scone-ratio"),
        (&["homography", "--data", "/nonexistent", "--ratio", "eight"], "--ratio"),
    ];
    for (args, flag) in cases {
        let (ok, err) = eval(args);
        assert!(!ok, "{args:?} was accepted");
        assert!(err.contains(flag) && err.contains("invalid value"), "{args:?}: {err}");
    }
    // In range, the ratio passes the parser and the command stops at the missing scene instead.
    let (ok, err) = eval(&["homography", "--data", "/nonexistent", "--ratio", "1", "--scone-ratio", "0.85"]);
    assert!(!ok && !err.contains("invalid value"), "{err}");
}
