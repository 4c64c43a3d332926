//! ARI against an independent implementation: scikit-learn's `adjusted_rand_score`.
//! `scripts/test` (the README's test command) installs scikit-learn.

use osrt_model::metrics::ari;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::io::Write;
use std::process::{Command, Stdio};

#[test]
fn ari_matches_scikit_learn() {
    let have = Command::new("python3")
        .args(["-c", "import sklearn"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    assert!(
        have,
        "python3 has no scikit-learn: run the tests with scripts/test, which installs it"
    );
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut cases = Vec::new();
    for i in 0..40 {
        let n = [1, 2, 5, 50, 1000, 20_000][i % 6];
        let kt = rng.random_range(1..8u32);
        let kp = rng.random_range(1..8u32);
        let truth: Vec<u32> = (0..n).map(|_| rng.random_range(0..kt)).collect();
        // Mix of agreeing and random predictions.
        let pred: Vec<u32> = truth
            .iter()
            .map(|&t| {
                if rng.random::<f64>() < 0.7 {
                    (t * 3 + 1) % 11
                } else {
                    rng.random_range(0..kp)
                }
            })
            .collect();
        cases.push((truth, pred));
    }
    let json = serde_json::to_string(&cases).unwrap();
    let mut child = Command::new("python3")
        .args([
            "-c",
            "import json,sys\nfrom sklearn.metrics import adjusted_rand_score as a\n\
             print(json.dumps([a(t,p) for t,p in json.load(sys.stdin)]))",
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(json.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    let want: Vec<f64> = serde_json::from_slice(&out.stdout).unwrap();
    for ((t, p), w) in cases.iter().zip(want) {
        let got = ari(t, p).unwrap();
        assert!(
            (got - w).abs() < 1e-9,
            "n = {}: ours {got}, scikit-learn {w}",
            t.len()
        );
    }
}
