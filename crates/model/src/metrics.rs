//! Evaluation metrics (REFERENCE.md "Metrics"), each with `update` / `compute` / `reset`.
//!
//! - **PSNR** = −10·log10(MSE) per scene, averaged over scenes. A perfect reconstruction
//!   (MSE = 0) is capped at [`PSNR_CAP_DB`] instead of +∞.
//! - **ARI** (adjusted Rand index) over all pixels; **FG-ARI** over pixels whose
//!   ground-truth id is not background (0). Both are pooled over **all target views of a
//!   scene together** — a slot must keep its object across views to score (3D
//!   consistency). **2D-FG-ARI** is the mean of per-view FG-ARI; the **ratio** FG-ARI /
//!   2D-FG-ARI is 1.0 for perfectly 3D-consistent segmentations.
//! - Contingency sums are in f64 (pair counts of a 128² image exceed f32's exact range).
//! - Single-cluster convention (as scikit-learn's `adjusted_rand_score`): when the index
//!   is 0/0 — both partitions are one cluster, or both put every pixel alone — the score
//!   is 1.0. A scene with no foreground pixels has no FG-ARI and is left out of the mean.

/// PSNR of a perfect reconstruction (MSE below 1e-10).
pub const PSNR_CAP_DB: f64 = 100.0;

/// PSNR in dB of one scene; values in `[0, 1]`. A prediction with a non-finite value
/// scores NaN (not the cap: `NaN.min(cap)` is the cap), so nothing ranks it best.
pub fn psnr(pred: &[f32], target: &[f32]) -> f64 {
    assert_eq!(pred.len(), target.len());
    let n = pred.len().max(1) as f64;
    let mse: f64 = pred
        .iter()
        .zip(target)
        .map(|(&p, &t)| {
            let d = p as f64 - t as f64;
            d * d
        })
        .sum::<f64>()
        / n;
    if !mse.is_finite() {
        f64::NAN
    } else if mse < 1e-10 {
        PSNR_CAP_DB
    } else {
        (-10.0 * mse.log10()).min(PSNR_CAP_DB)
    }
}

/// Mean PSNR over scenes.
#[derive(Debug, Default, Clone)]
pub struct Psnr {
    sum: f64,
    count: usize,
}

impl Psnr {
    pub fn update(&mut self, pred: &[f32], target: &[f32]) {
        self.sum += psnr(pred, target);
        self.count += 1;
    }
    pub fn compute(&self) -> Option<f64> {
        (self.count > 0).then(|| self.sum / self.count as f64)
    }
    pub fn reset(&mut self) {
        *self = Self::default();
    }
}

fn comb2(n: f64) -> f64 {
    n * (n - 1.0) / 2.0
}

/// Adjusted Rand index between two labelings of the same points (labels are arbitrary
/// small integers). `None` for an empty input.
pub fn ari(truth: &[u32], pred: &[u32]) -> Option<f64> {
    assert_eq!(truth.len(), pred.len());
    if truth.is_empty() {
        return None;
    }
    let nt = *truth.iter().max().unwrap() as usize + 1;
    let np = *pred.iter().max().unwrap() as usize + 1;
    let mut table = vec![0f64; nt * np];
    for (&t, &p) in truth.iter().zip(pred) {
        table[t as usize * np + p as usize] += 1.0;
    }
    let mut rows = vec![0f64; nt];
    let mut cols = vec![0f64; np];
    let mut index = 0.0;
    for t in 0..nt {
        for p in 0..np {
            let c = table[t * np + p];
            rows[t] += c;
            cols[p] += c;
            index += comb2(c);
        }
    }
    let sum_rows: f64 = rows.iter().map(|&a| comb2(a)).sum();
    let sum_cols: f64 = cols.iter().map(|&b| comb2(b)).sum();
    let total = comb2(truth.len() as f64);
    let expected = if total > 0.0 {
        sum_rows * sum_cols / total
    } else {
        0.0
    };
    let max = 0.5 * (sum_rows + sum_cols);
    let denom = max - expected;
    if denom.abs() < 1e-12 {
        // 0/0: both one cluster or both all singletons — identical partitions.
        return Some(1.0);
    }
    Some((index - expected) / denom)
}

/// ARI over foreground points only (ground truth ≠ 0). `None` when there are none.
pub fn fg_ari(truth: &[u8], pred: &[u32]) -> Option<f64> {
    let (t, p): (Vec<u32>, Vec<u32>) = truth
        .iter()
        .zip(pred)
        .filter(|&(&t, _)| t != 0)
        .map(|(&t, &p)| (t as u32, p))
        .unzip();
    ari(&t, &p)
}

/// ARI, FG-ARI (pooled over a scene's views), 2D-FG-ARI (per view, averaged) and their
/// ratio, averaged over scenes.
#[derive(Debug, Default, Clone)]
pub struct Segmentation {
    ari: (f64, usize),
    fg_ari: (f64, usize),
    fg_ari_2d: (f64, usize),
}

/// Means of [`Segmentation`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentationScores {
    pub ari: Option<f64>,
    pub fg_ari: Option<f64>,
    pub fg_ari_2d: Option<f64>,
    pub ratio: Option<f64>,
}

impl Segmentation {
    /// One scene: per target view, the ground-truth ids and the predicted slot per pixel.
    pub fn update(&mut self, views: &[(&[u8], &[u32])]) {
        let truth: Vec<u8> = views.iter().flat_map(|(t, _)| t.iter().copied()).collect();
        let pred: Vec<u32> = views.iter().flat_map(|(_, p)| p.iter().copied()).collect();
        let truth32: Vec<u32> = truth.iter().map(|&t| t as u32).collect();
        if let Some(a) = ari(&truth32, &pred) {
            self.ari.0 += a;
            self.ari.1 += 1;
        }
        if let Some(a) = fg_ari(&truth, &pred) {
            self.fg_ari.0 += a;
            self.fg_ari.1 += 1;
        }
        let per_view: Vec<f64> = views.iter().filter_map(|(t, p)| fg_ari(t, p)).collect();
        if !per_view.is_empty() {
            self.fg_ari_2d.0 += per_view.iter().sum::<f64>() / per_view.len() as f64;
            self.fg_ari_2d.1 += 1;
        }
    }

    pub fn compute(&self) -> SegmentationScores {
        let mean = |(s, n): (f64, usize)| (n > 0).then(|| s / n as f64);
        let fg = mean(self.fg_ari);
        let fg2 = mean(self.fg_ari_2d);
        SegmentationScores {
            ari: mean(self.ari),
            fg_ari: fg,
            fg_ari_2d: fg2,
            ratio: match (fg, fg2) {
                (Some(a), Some(b)) if b.abs() > 1e-12 => Some(a / b),
                _ => None,
            },
        }
    }

    pub fn reset(&mut self) {
        *self = Self::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_is_finite_and_capped_for_perfect_reconstructions() {
        assert_eq!(psnr(&[0.5, 0.2], &[0.5, 0.2]), PSNR_CAP_DB);
        // MSE 0.01 → 20 dB.
        assert!((psnr(&[0.1], &[0.2]) - 20.0).abs() < 1e-6);
        let mut m = Psnr::default();
        assert_eq!(m.compute(), None);
        m.update(&[0.1], &[0.2]);
        m.update(&[0.0], &[0.01]);
        assert!((m.compute().unwrap() - 30.0).abs() < 1e-6);
        m.reset();
        assert_eq!(m.compute(), None);
    }

    #[test]
    fn a_non_finite_prediction_scores_nan_not_the_cap() {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            assert!(psnr(&[0.5, bad], &[0.5, 0.2]).is_nan(), "{bad}");
            let mut m = Psnr::default();
            m.update(&[0.1], &[0.2]);
            m.update(&[bad], &[0.2]);
            assert!(m.compute().is_none_or(|p| p.is_nan()), "{bad}");
        }
    }

    #[test]
    fn ari_hand_worked_cases() {
        // Identical partitions up to relabelling.
        assert_eq!(ari(&[0, 0, 1, 1], &[5, 5, 2, 2]), Some(1.0));
        // Worked by hand: truth {0,0,1,1}, pred {0,1,0,1}: n_ij all 1 → index 0;
        // Σ C(a,2) = 2, Σ C(b,2) = 2, C(4,2) = 6 → expected 2/3, max 2 → ARI = −0.5.
        assert!((ari(&[0, 0, 1, 1], &[0, 1, 0, 1]).unwrap() + 0.5).abs() < 1e-12);
        // truth {0,0,0,1,1,1}, pred {0,0,1,1,2,2}: index = 1+0+0+1 = 2 (C(2,2) twice);
        // rows 3,3 → 3+3 = 6; cols 2,2,2 → 3; total 15; expected 6·3/15 = 1.2;
        // max 4.5 → (2 − 1.2)/(4.5 − 1.2) = 0.2424…
        let v = ari(&[0, 0, 0, 1, 1, 1], &[0, 0, 1, 1, 2, 2]).unwrap();
        assert!((v - 0.8 / 3.3).abs() < 1e-12, "{v}");
        // Single cluster on both sides: 0/0 → 1 by convention.
        assert_eq!(ari(&[3, 3, 3], &[1, 1, 1]), Some(1.0));
        // One truth cluster, prediction splits it: 0.
        assert_eq!(ari(&[1, 1, 1, 1], &[0, 0, 1, 1]), Some(0.0));
        assert_eq!(ari(&[], &[]), None);
    }

    #[test]
    fn fg_ari_ignores_background_and_pools_views() {
        // Background (0) labelled anything: no effect.
        let truth = [0, 0, 1, 1, 2, 2];
        assert_eq!(fg_ari(&truth, &[7, 3, 0, 0, 1, 1]), Some(1.0));
        assert_eq!(fg_ari(&[0, 0], &[1, 2]), None);
        // Two views, each perfectly segmented, but the slot for object 1 changes between
        // views: 2D-FG-ARI is 1, pooled FG-ARI is not.
        let mut m = Segmentation::default();
        let (t1, p1) = ([1u8, 1, 2, 2], [0u32, 0, 1, 1]);
        let (t2, p2) = ([1u8, 1, 2, 2], [1u32, 1, 0, 0]);
        m.update(&[(&t1, &p1), (&t2, &p2)]);
        let s = m.compute();
        assert_eq!(s.fg_ari_2d, Some(1.0));
        assert!(s.fg_ari.unwrap() < 0.0, "{s:?}");
        assert!(s.ratio.unwrap() < 0.0);
        m.reset();
        m.update(&[(&t1, &p1), (&t2, &p1)]);
        assert_eq!(m.compute().fg_ari, Some(1.0));
        assert_eq!(m.compute().ratio, Some(1.0));
    }

    #[test]
    fn large_images_stay_exact_in_f64() {
        // 3 views of 256² pixels: pair counts ≈ 2·10¹¹, beyond f32's exact integers.
        let n = 3 * 256 * 256;
        let truth: Vec<u32> = (0..n).map(|i| (i % 5) as u32).collect();
        let pred: Vec<u32> = (0..n).map(|i| ((i % 5) + 1) as u32 % 5).collect();
        assert_eq!(ari(&truth, &pred), Some(1.0));
    }
}
