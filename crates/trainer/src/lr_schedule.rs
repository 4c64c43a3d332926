//! The learning-rate schedule: a linear warm-up to the peak `lr`, then an exponential
//! decay, and where that decay ends (its *horizon*).
//!
//! `train.horizon` chooses the horizon:
//! - `fixed` (the default): `lr · decay_rate^((step − warmup) / decay_steps)`, on and on.
//!   A host twice as fast ends the same minutes twice as far down the curve.
//! - `budget`: the decay reaches its floor `lr · decay_rate` at the job's last step and
//!   stays there: `lr · decay_rate^min(1, (step − warmup) / (H − warmup))`. With
//!   `--max-steps` alone, `H` is that step count. With `--max-minutes`, rank 0 measures
//!   the step rate over the warm-up and fixes `H` from the time left (less the
//!   validations still to come), every rank receives it with the all-reduce of the last
//!   warm-up step, and it is recorded in `run.json` and every checkpoint, so that a
//!   resume keeps it and a rerun given it (`horizon = H`) takes the same steps to the bit:
//!   reproducibility is a property of (config, horizon), not of the host's speed.
//! - a step count `H`: the budget's formula with that horizon.
//!
//! A budget job with no budget (neither limit) follows `decay_steps`, as `fixed` does,
//! until a horizon is known.

use serde::{Deserialize, Serialize};

/// Largest horizon: it travels through the all-reduce as one f32, exact up to 2^24.
pub const MAX_HORIZON: u64 = 1 << 24;

/// Steps of a generation left out of the rate (allocation, first-touch and compile costs
/// of the first steps): a quarter of the warm-up, at most this many.
const SKIP_STEPS: u64 = 50;
/// Steps the rate is measured over before a horizon is proposed: this many, or all the
/// warm-up leaves after the skipped steps (at least one).
const MIN_MEASURED_STEPS: u64 = 5;

/// Where the decay ends (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Horizon {
    #[default]
    Fixed,
    Budget,
    Steps(u64),
}

impl Horizon {
    pub fn is_fixed(&self) -> bool {
        *self == Horizon::Fixed
    }
}

/// TOML: `"fixed"`, `"budget"` or a step count.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum HorizonRepr {
    Steps(u64),
    Name(String),
}

impl Serialize for Horizon {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match *self {
            Horizon::Fixed => HorizonRepr::Name("fixed".into()),
            Horizon::Budget => HorizonRepr::Name("budget".into()),
            Horizon::Steps(n) => HorizonRepr::Steps(n),
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for Horizon {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        match HorizonRepr::deserialize(d)? {
            HorizonRepr::Steps(n) => Ok(Horizon::Steps(n)),
            HorizonRepr::Name(s) => s.parse().map_err(serde::de::Error::custom),
        }
    }
}

impl std::str::FromStr for Horizon {
    type Err = String;
    /// `fixed`, `budget` or a step count (the `--horizon` flag, the sweep axis).
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "fixed" => Ok(Horizon::Fixed),
            "budget" => Ok(Horizon::Budget),
            n => n.parse().map(Horizon::Steps).map_err(|_| {
                format!("unknown horizon `{s}`: expected fixed, budget or a step count")
            }),
        }
    }
}

impl std::fmt::Display for Horizon {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Horizon::Fixed => write!(f, "fixed"),
            Horizon::Budget => write!(f, "budget"),
            Horizon::Steps(n) => write!(f, "{n}"),
        }
    }
}

/// The schedule's settings (from `TrainConfig`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule {
    pub lr: f64,
    pub warmup_steps: u64,
    pub decay_rate: f64,
    pub decay_steps: f64,
    pub horizon: Horizon,
}

impl Schedule {
    /// The horizon known before the first step: the config's step count, or a budget
    /// job's step limit when it has no deadline (with a deadline the rate decides, and
    /// the step limit caps what it gives).
    pub fn initial_horizon(&self, max_steps: Option<u64>, has_deadline: bool) -> Option<u64> {
        match self.horizon {
            Horizon::Fixed => None,
            Horizon::Steps(n) => Some(n),
            Horizon::Budget if has_deadline => None,
            Horizon::Budget => max_steps,
        }
    }

    /// Learning rate at `step` (0-based), with `resolved` the horizon in force (ignored
    /// by a fixed schedule).
    pub fn lr_at(&self, step: u64, resolved: Option<u64>) -> f64 {
        let w = self.warmup_steps;
        if step < w {
            return self.lr * (step + 1) as f64 / w as f64;
        }
        let after = (step - w) as f64;
        let exponent = match (self.horizon, resolved) {
            (Horizon::Fixed, _) | (_, None) => after / self.decay_steps,
            (_, Some(h)) if h <= w => 1.0,
            (_, Some(h)) => (after / (h - w) as f64).min(1.0),
        };
        self.lr * self.decay_rate.powf(exponent)
    }
}

/// Rank 0's measure of the step rate, for a budget job with a deadline. Times are Unix
/// seconds (the deadline's clock); validation time is taken out of the rate and put
/// back, per validation still to come, into the time left.
#[derive(Debug, Clone, Default)]
pub struct RateClock {
    /// Steps this generation has finished, and how many of the first are left out.
    steps: u64,
    skip: u64,
    /// (step, time, validation seconds so far) where measuring began.
    mark: Option<(u64, f64, f64)>,
    /// Seconds spent validating in this generation, and the last validation's length.
    eval_total_s: f64,
    last_eval_s: f64,
}

impl RateClock {
    /// A validation of `seconds` ran.
    pub fn evaluated(&mut self, seconds: f64) {
        self.eval_total_s += seconds;
        self.last_eval_s = seconds;
    }

    /// The generation's steps begin at step `step`, at `now`; measuring begins after
    /// its first `min(SKIP_STEPS, warmup / 4)` steps.
    pub fn start(&mut self, step: u64, now: f64, warmup: u64) {
        self.steps = 0;
        self.skip = (warmup / 4).min(SKIP_STEPS);
        self.mark = (self.skip == 0).then_some((step, now, self.eval_total_s));
    }

    /// Step `step − 1` finished at `now` (`step` is the next to run).
    pub fn stepped(&mut self, step: u64, now: f64) {
        self.steps += 1;
        if self.mark.is_none() && self.steps >= self.skip {
            self.mark = Some((step, now, self.eval_total_s));
        }
    }

    /// The horizon to propose while step `step` (0-based, the next to apply) runs at
    /// `now`: from the last warm-up step on (so that the first decayed step has it), once
    /// the rate is measured over enough steps. The steps the time left allows at the
    /// measured rate (validations every `eval_every_s`, each as long as the last one,
    /// taken out), capped by `max_steps` and [`MAX_HORIZON`].
    pub fn propose(
        &self,
        step: u64,
        now: f64,
        deadline: f64,
        warmup: u64,
        eval_every_s: f64,
        max_steps: Option<u64>,
    ) -> Option<u64> {
        let (m_step, m_time, m_eval) = self.mark?;
        let measured = step.checked_sub(m_step)?;
        let enough = warmup
            .saturating_sub(1 + self.skip)
            .clamp(1, MIN_MEASURED_STEPS);
        if step + 1 < warmup || measured < enough {
            return None;
        }
        let busy = (now - m_time - (self.eval_total_s - m_eval)).max(1e-9);
        let rate = measured as f64 / busy;
        let left = (deadline - now).max(0.0);
        let evals = (left / eval_every_s).floor();
        let usable = (left - evals * self.last_eval_s).max(0.0);
        let h = step.saturating_add((rate * usable).round() as u64);
        Some(h.min(max_steps.unwrap_or(u64::MAX)).clamp(1, MAX_HORIZON))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schedule(horizon: Horizon) -> Schedule {
        Schedule {
            lr: 1e-3,
            warmup_steps: 10,
            decay_rate: 0.1,
            decay_steps: 100.0,
            horizon,
        }
    }

    #[test]
    fn a_budget_decays_to_its_floor_at_the_horizon_and_stays() {
        let s = schedule(Horizon::Budget);
        let h = Some(110);
        assert_eq!(s.lr_at(0, h), 1e-4);
        assert_eq!(s.lr_at(9, h), 1e-3);
        assert_eq!(s.lr_at(10, h), 1e-3);
        assert!((s.lr_at(60, h) - 1e-3 * 0.1f64.sqrt()).abs() < 1e-15);
        assert!((s.lr_at(110, h) - 1e-4).abs() < 1e-18);
        assert_eq!(s.lr_at(110, h), s.lr_at(5_000, h));
        // A horizon inside the warm-up: the floor right after it.
        assert!((s.lr_at(10, Some(4)) - 1e-4).abs() < 1e-18);
        // Unknown yet: decay_steps, as a fixed schedule.
        assert_eq!(s.lr_at(60, None), schedule(Horizon::Fixed).lr_at(60, None));
        // A fixed schedule ignores a horizon and keeps decaying.
        let f = schedule(Horizon::Fixed);
        assert_eq!(f.lr_at(310, Some(110)), f.lr_at(310, None));
        assert!((f.lr_at(310, None) - 1e-6).abs() < 1e-18);
    }

    #[test]
    fn the_initial_horizon_comes_from_the_config_or_the_step_limit() {
        let b = schedule(Horizon::Budget);
        assert_eq!(b.initial_horizon(Some(500), false), Some(500));
        assert_eq!(b.initial_horizon(Some(500), true), None);
        assert_eq!(b.initial_horizon(None, false), None);
        let s = schedule(Horizon::Steps(700));
        assert_eq!(s.initial_horizon(Some(500), true), Some(700));
        assert_eq!(
            schedule(Horizon::Fixed).initial_horizon(Some(5), false),
            None
        );
    }

    #[test]
    fn the_rate_clock_leaves_out_the_first_steps_and_the_validations() {
        let mut c = RateClock::default();
        // Warm-up 40: the first 10 steps are left out. Step 0 takes 5 s, then 10 steps/s.
        let mut t = 1_000.0;
        c.start(0, t, 40);
        // Steps 0..=38 done; step 39, the last of the warm-up, runs.
        for step in 0..39 {
            t += if step == 0 { 5.0 } else { 0.1 };
            c.stepped(step + 1, t);
            if step == 20 {
                // A 3 s validation inside the window does not slow the measured rate.
                c.evaluated(3.0);
                t += 3.0;
            }
        }
        assert_eq!(
            c.propose(30, t, t + 100.0, 40, 1e9, None),
            None,
            "in warm-up"
        );
        // 100 s left with a validation every 30 s (3 of them, 3 s each): 91 s at 10/s.
        let h = c.propose(39, t, t + 100.0, 40, 30.0, None).unwrap();
        assert_eq!(h, 39 + 910);
        assert_eq!(c.propose(39, t, t + 100.0, 40, 30.0, Some(500)), Some(500));
        assert_eq!(c.propose(39, t, t - 5.0, 40, 30.0, None), Some(39));
        let far = c.propose(39, t, t + 1e12, 40, 1e9, None).unwrap();
        assert_eq!(far, MAX_HORIZON);
    }

    #[test]
    fn a_short_warm_up_still_decides_the_horizon_before_the_decay() {
        // Warm-up 2: nothing left out, the one step before the last warm-up step measured.
        let mut c = RateClock::default();
        c.start(0, 100.0, 2);
        assert_eq!(c.propose(0, 100.0, 200.0, 2, 1e9, None), None);
        c.stepped(1, 100.5);
        assert_eq!(c.propose(1, 100.5, 200.5, 2, 1e9, None), Some(1 + 200));
        // Warm-up 0: the first step measures, the decay before it follows decay_steps.
        let mut c = RateClock::default();
        c.start(7, 100.0, 0);
        assert_eq!(c.propose(7, 100.0, 200.0, 0, 1e9, None), None);
        c.stepped(8, 101.0);
        assert_eq!(c.propose(8, 101.0, 200.0, 0, 1e9, None), Some(8 + 99));
    }

    #[test]
    fn horizons_read_and_write_as_the_config_spells_them() {
        for (text, h) in [
            ("\"fixed\"", Horizon::Fixed),
            ("\"budget\"", Horizon::Budget),
            ("4700", Horizon::Steps(4700)),
        ] {
            let t: toml::Table = format!("h = {text}").parse().unwrap();
            let got: Horizon = t["h"].clone().try_into().unwrap();
            assert_eq!(got, h);
            assert_eq!(h.to_string().parse::<Horizon>().unwrap(), h);
        }
        let bad: toml::Table = "h = \"soon\"".parse().unwrap();
        let err = bad["h"].clone().try_into::<Horizon>().unwrap_err();
        assert!(
            err.to_string()
                .contains("expected fixed, budget or a step count")
        );
        assert!("-3".parse::<Horizon>().is_err());
    }
}
