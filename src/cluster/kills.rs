//! The local launcher's watch on its workers' SIGKILLs: a worker killed twice at the same
//! point of the job would be killed again however often it is replaced.

use osrt_trainer::device::DeviceSpec;

/// Where the job was when a worker was killed: at a step, or setting a generation up
/// from a checkpoint (the heartbeats' step is 0 then, whatever the job's step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Point {
    Step(u64),
    Setup(Option<u64>),
}

impl Point {
    /// The point of the job's status: its ranks' step, or during a generation's set-up
    /// (step 0), the checkpoint the generation starts from.
    pub(super) fn of(step: u64, last_checkpoint: Option<u64>) -> Self {
        if step > 0 {
            Point::Step(step)
        } else {
            Point::Setup(last_checkpoint)
        }
    }
}

impl std::fmt::Display for Point {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Point::Step(s) => write!(f, "at step {s}"),
            Point::Setup(Some(c)) => write!(f, "while setting up from checkpoint {c}"),
            Point::Setup(None) => write!(f, "while setting up the job's first step"),
        }
    }
}

/// One local worker slot's SIGKILLs: a worker killed twice at the same point of the job
/// (the kernel's out-of-memory killer, most likely: it kills with SIGKILL) would be
/// killed again however often it is replaced.
#[derive(Default)]
pub(super) struct Kills {
    /// Where the job was when this slot's worker was last killed.
    at: Option<Point>,
    /// The worker's resident memory when last sampled, in MiB.
    rss_mb: Option<f64>,
}

impl Kills {
    /// Samples the running worker's resident memory (Linux: `VmRSS`).
    pub(super) fn sample(&mut self, child: &tokio::process::Child) {
        let rss = child.id().and_then(|pid| {
            let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
            let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
            line.split_whitespace().nth(1)?.parse::<f64>().ok()
        });
        if let Some(kib) = rss {
            self.rss_mb = Some(kib / 1024.0);
        }
    }

    /// Why the job must end, where worker `k`'s `exit` is its second SIGKILL at `at`.
    pub(super) fn killed_again(
        &mut self,
        k: usize,
        exit: std::process::ExitStatus,
        at: Point,
    ) -> Option<String> {
        use std::os::unix::process::ExitStatusExt;
        if exit.signal() != Some(9) {
            self.at = None;
            return None;
        }
        if self.at.replace(at) != Some(at) {
            return None;
        }
        let rss = self.rss_mb.map_or(String::new(), |mb| {
            format!(", last seen at {:.2} GiB resident", mb / 1024.0)
        });
        let machine = osrt_trainer::footprint::machine_memory(DeviceSpec::Cpu)
            .map_or(String::new(), |(b, what)| {
                format!(" ({what}: {:.2} GiB)", b / (1u64 << 30) as f64)
            });
        Some(format!(
            "worker {k} was killed by SIGKILL twice {at}{rss}{machine}: the kernel's \
             out-of-memory killer, most likely, and a replacement would meet the same end. \
             Make the step smaller (--recompute, --batch-size, --rays-per-scene, fewer workers, smaller \
             images: osrt data import --resize) or run on a machine with more memory"
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::process::ExitStatusExt;

    /// Kills during set-up are told apart by the checkpoint the generation starts from
    /// (the heartbeats' step is 0 in every set-up): one at step 40 and one setting up from
    /// checkpoint 40 are different points, two set-ups from checkpoint 40 the same.
    #[test]
    fn setup_kills_are_keyed_by_the_generations_start() {
        let kill = std::process::ExitStatus::from_raw(9);
        let mut k = Kills::default();
        assert!(k.killed_again(0, kill, Point::of(40, Some(40))).is_none());
        assert!(k.killed_again(0, kill, Point::of(0, Some(40))).is_none());
        assert!(k.killed_again(0, kill, Point::of(0, Some(20))).is_none());
        let why = k.killed_again(0, kill, Point::of(0, Some(20))).unwrap();
        assert!(
            why.contains("twice while setting up from checkpoint 20"),
            "{why}"
        );
        let mut k = Kills::default();
        assert!(k.killed_again(1, kill, Point::of(57, Some(50))).is_none());
        let why = k.killed_again(1, kill, Point::of(57, Some(50))).unwrap();
        assert!(why.contains("twice at step 57"), "{why}");
    }
}
