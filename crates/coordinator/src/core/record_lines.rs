//! Rank 0's record lines as the state machine takes them: one record per line, so
//! `metrics.jsonl` reads back as it was written.

use super::tests::{reg, spec, tick};
use super::*;

/// A running one-worker job; returns the core and its worker's id.
fn running(t: Instant) -> (Core, u64) {
    let mut c = Core::new(spec(1, 1, 3), t);
    let id = reg(&mut c, t);
    tick(&mut c, t);
    assert_eq!(c.phase, Phase::Running);
    (c, id)
}

fn report(id: u64, step: u64, records: &[&str]) -> Progress {
    Progress {
        worker_id: id,
        generation: 1,
        rank: 0,
        step,
        param_hash: None,
        records: records.iter().map(|l| l.to_string()).collect(),
    }
}

/// A record spread over lines is valid JSON, yet stored it would split the file: the
/// report is refused whole, and the file holds one record per line.
#[test]
fn a_record_line_with_a_line_break_is_refused_and_nothing_of_its_report_stored() {
    let t = Instant::now();
    let (mut c, id) = running(t);
    c.progress(report(id, 1, &[r#"{"loss":0.5,"step":1}"#]), t)
        .unwrap();
    for bad in [
        "{\"loss\":0.5,\n\"step\":2}",
        "{\"loss\":0.5,\"step\":2}\r\n",
    ] {
        let e = c
            .progress(report(id, 2, &[r#"{"loss":0.4,"step":2}"#, bad]), t)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
        assert!(
            e.message().contains("record 1 of the report") && e.message().contains("line break"),
            "{e}"
        );
    }
    let e = c
        .progress(report(id, 2, &[r#"{"step":2}"#]), t)
        .unwrap_err();
    assert!(e.message().contains("not one JSON object"), "{e}");
    assert_eq!(c.records.len(), 1, "{:?}", c.records);
    // The worker's next report carries them again, well formed.
    c.progress(report(id, 2, &[r#"{"loss":0.4,"step":2}"#]), t)
        .unwrap();
    let lines = c.metrics_write().lines;
    let steps: Vec<u64> = lines.iter().map(|(_, l)| record_step(l).unwrap()).collect();
    assert_eq!(steps, [1, 2], "{lines:?}");
}
