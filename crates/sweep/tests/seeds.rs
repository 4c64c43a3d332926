//! Seed groups from real run folders: `metrics.jsonl` files written the way runs write
//! them, read back through `RunSummary`, grouped, averaged, timed to targets and written
//! as a report.

use osrt_sweep::html::{self, Report};
use osrt_sweep::plot::Metric;
use osrt_sweep::seeds::{Group, MeanCurve, Member, SeedReport, Target, TargetError};
use osrt_sweep::{Curve, Point, PointResult, RunSummary, SweepFile};
use std::path::Path;

/// One seed's evaluations `(wall_s, step, psnr, fg_ari)`, with training records between
/// them as a run writes, into `dir/metrics.jsonl`; read back as a run's curve.
fn run(dir: &Path, label: &str, evals: &[(f64, u64, f64, Option<f64>)]) -> Curve {
    std::fs::create_dir_all(dir).unwrap();
    let mut text = String::new();
    for &(wall_s, step, psnr, fg) in evals {
        text.push_str(&format!(
            "{{\"epoch\":0,\"loss\":0.05,\"lr\":0.0001,\"scenes_per_s\":4.0,\"step\":{step},\
             \"train_s\":{t},\"wall_s\":{t},\"workers\":2}}\n",
            t = wall_s - 1.0
        ));
        let fg = fg.map_or("null".to_string(), |v| v.to_string());
        text.push_str(&format!(
            "{{\"baseline_psnr\":15.0,\"eval_scenes\":4,\"fg_ari\":{fg},\"psnr\":{psnr},\
             \"render_fps\":10.0,\"step\":{step},\"train_s\":{wall_s},\"wall_s\":{wall_s}}}\n"
        ));
    }
    std::fs::write(dir.join("metrics.jsonl"), text).unwrap();
    RunSummary::load(dir).unwrap().curve(label)
}

fn result(point: &str, psnr: f64, fg_ari: Option<f64>) -> PointResult {
    PointResult {
        point: point.into(),
        settings: Vec::new(),
        train_wall_s: 30.0,
        steps: 300,
        scenes_per_s: 4.0,
        eval_split: "test".into(),
        eval_scenes: 4,
        psnr,
        baseline_psnr: 15.0,
        fg_ari,
        ari: fg_ari,
        fg_ari_2d: fg_ari,
        ratio: None,
        render_fps: 10.0,
        peak_rss_mb: None,
    }
}

/// Three seeds evaluated about every 10 s, each on its own clock. Seed 1 reaches FG-ARI
/// 0.5 exactly at 21 s; seed 2 never reaches it (0.45 at best); seed 0 passes it at 30 s.
fn three_seeds(root: &Path) -> Vec<(Point, Curve, Option<PointResult>)> {
    let seeds = [
        (
            "0",
            vec![
                (10.0, 100, 20.0, Some(0.2)),
                (20.0, 200, 22.0, Some(0.4)),
                (30.0, 300, 24.0, Some(0.6)),
            ],
            Some(result("s0", 24.5, Some(0.8))),
        ),
        (
            "1",
            vec![
                (11.0, 110, 21.0, Some(0.3)),
                (21.0, 210, 23.0, Some(0.5)),
                (31.0, 310, 25.0, Some(0.9)),
            ],
            Some(result("s1", 25.5, Some(0.9))),
        ),
        (
            "2",
            vec![
                (12.0, 120, 19.0, Some(0.1)),
                (22.0, 220, 20.0, Some(0.3)),
                (29.0, 290, 21.0, Some(0.45)),
            ],
            None,
        ),
    ];
    seeds
        .into_iter()
        .map(|(seed, evals, result)| {
            let name = format!("lr=0.001,seed={seed}");
            let curve = run(&root.join(&name), &name, &evals);
            let settings = vec![("lr".into(), "0.001".into()), ("seed".into(), seed.into())];
            (Point { settings }, curve, result)
        })
        .collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

/// The mean curve is taken at the union of the seeds' evaluation times inside the span
/// all of them cover (12 s to 29 s), each seed linear between its evaluations.
#[test]
fn mean_and_spread_are_taken_at_the_union_of_evaluation_times() {
    let dir = tempfile::tempdir().unwrap();
    let groups = Group::by_settings(three_seeds(dir.path()));
    assert_eq!(groups.len(), 1);
    let curves: Vec<Curve> = groups[0].members.iter().map(|m| m.curve.clone()).collect();
    let fg = MeanCurve::new(&curves, Metric::FgAri);
    assert_eq!(fg.seeds, 3);
    let times: Vec<f64> = fg.points.iter().map(|p| p.wall_s).collect();
    assert_eq!(times, [12.0, 20.0, 21.0, 22.0, 29.0]);
    // At 12 s: seed 0 is 2/10 of the way from 0.2 to 0.4, seed 1 1/10 from 0.3 to 0.5,
    // seed 2 evaluated there (0.1).
    let first = fg.points[0];
    assert!(
        close(first.value.mean, (0.24 + 0.32 + 0.1) / 3.0),
        "{first:?}"
    );
    assert!(close(first.value.min, 0.1) && close(first.value.max, 0.32));
    assert!(close(first.step, 120.0), "{first:?}");
    // At 29 s: 0.4 + 0.9·0.2, 0.5 + 0.8·0.4, and seed 2's last evaluation.
    let last = fg.points[4];
    assert!(
        close(last.value.mean, (0.58 + 0.82 + 0.45) / 3.0),
        "{last:?}"
    );
    assert!(close(last.value.min, 0.45) && close(last.value.max, 0.82));
    let psnr = MeanCurve::new(&curves, Metric::Psnr);
    // At 20 s: seed 0's evaluation, seed 1 9/10 from 21 to 23 dB, seed 2 8/10 from 19
    // to 20 dB.
    assert!(close(psnr.points[1].value.mean, (22.0 + 22.8 + 19.8) / 3.0));

    // One seed: its own curve, no spread.
    let one = MeanCurve::new(&curves[..1], Metric::Psnr);
    let got: Vec<(f64, f64, f64)> = one
        .points
        .iter()
        .map(|p| (p.wall_s, p.value.min, p.value.max))
        .collect();
    assert_eq!(
        got,
        [(10.0, 20.0, 20.0), (20.0, 22.0, 22.0), (30.0, 24.0, 24.0)]
    );
}

/// A seed without FG-ARI at all (a decoder without slots) is left out of that mean, not
/// counted as zero; curves that share no time have no mean.
#[test]
fn seeds_without_a_metric_or_a_common_span_are_not_averaged_in() {
    let dir = tempfile::tempdir().unwrap();
    let a = run(
        &dir.path().join("a"),
        "a",
        &[(10.0, 1, 20.0, Some(0.5)), (20.0, 2, 21.0, Some(0.7))],
    );
    let b = run(
        &dir.path().join("b"),
        "b",
        &[(10.0, 1, 22.0, None), (20.0, 2, 23.0, None)],
    );
    let fg = MeanCurve::new(&[a.clone(), b.clone()], Metric::FgAri);
    assert_eq!(fg.seeds, 1);
    assert_eq!(fg.points.len(), 2);
    assert!(close(fg.points[1].value.mean, 0.7));
    let psnr = MeanCurve::new(&[a.clone(), b], Metric::Psnr);
    assert_eq!((psnr.seeds, psnr.points[0].value.mean), (2, 21.0));
    let late = run(&dir.path().join("c"), "c", &[(30.0, 3, 20.0, None)]);
    assert!(MeanCurve::new(&[a, late], Metric::Psnr).points.is_empty());
}

#[test]
fn time_to_target_is_the_first_evaluation_at_or_above_it() {
    let dir = tempfile::tempdir().unwrap();
    let groups = Group::by_settings(three_seeds(dir.path()));
    let targets: Vec<Target> = ["fg_ari=0.5", "psnr=30", "fg_ari=0.2"]
        .iter()
        .map(|t| t.parse().unwrap())
        .collect();
    let report = SeedReport::new(&groups, &targets);
    let g = &report.groups[0];
    let hits = |i: usize| -> Vec<Option<(f64, u64)>> {
        g.targets[i]
            .hits
            .iter()
            .map(|h| h.map(|h| (h.wall_s, h.step)))
            .collect()
    };
    // Seed 1 equals the target exactly at 21 s; seed 2's best (0.45) is below it.
    assert_eq!(hits(0), [Some((30.0, 300)), Some((21.0, 210)), None]);
    assert_eq!(g.targets[0].reached(), 2);
    assert_eq!(g.targets[0].mean(), Some((25.5, 255.0)));
    // Never reached by any seed.
    assert_eq!(hits(1), [None, None, None]);
    assert_eq!(g.targets[1].mean(), None);
    // Reached at the first evaluation by seeds 0 and 1 (0.2, 0.3), at 22 s by seed 2.
    assert_eq!(
        hits(2),
        [Some((10.0, 100)), Some((11.0, 110)), Some((22.0, 220))]
    );

    // Just below the threshold is not reaching it.
    let below: Target = "fg_ari=0.5000001".parse().unwrap();
    assert_eq!(
        below.first_hit(&groups[0].members[1].curve).map(|h| h.step),
        Some(310)
    );
}

#[test]
fn targets_that_cannot_be_read_say_why() {
    let t: Target = " psnr = 28 ".parse().unwrap();
    assert_eq!((t.metric, t.value), (Metric::Psnr, 28.0));
    let t: Target = "fg_ari=0.85".parse().unwrap();
    assert_eq!(t.to_string(), "fg_ari>=0.85");
    assert_eq!(
        "ari=0.5".parse::<Target>(),
        Err(TargetError::UnknownMetric {
            spec: "ari=0.5".into(),
            metric: "ari".into()
        })
    );
    for bad in ["psnr=abc", "psnr=", "fg_ari=nan", "psnr=inf"] {
        let e = bad.parse::<Target>().unwrap_err();
        assert!(matches!(e, TargetError::NotANumber { .. }), "{bad}: {e:?}");
        assert!(e.to_string().contains("is not a finite number"), "{e}");
    }
    let e = "fg_ari".parse::<Target>().unwrap_err();
    assert_eq!(e, TargetError::Syntax("fg_ari".into()));
    assert!(e.to_string().contains("METRIC=VALUE"), "{e}");
    let e = "loss=0.1".parse::<Target>().unwrap_err().to_string();
    assert!(
        e.contains("unknown metric `loss`") && e.contains("fg_ari or psnr"),
        "{e}"
    );
}

fn empty() -> Curve {
    Curve {
        label: String::new(),
        points: Vec::new(),
    }
}

/// Points that differ only in the seed are one group; without a seed axis each point is
/// its own group; a sweep of seeds alone is one group, `base`.
#[test]
fn points_are_grouped_by_their_settings_without_the_seed() {
    let grouped = |axes: &str| -> Vec<(String, Vec<String>)> {
        let text = format!("name = \"g\"\npreset = \"tiny\"\nmax_steps = 1\n[axes]\n{axes}\n");
        let f = SweepFile::parse(&text, "g.toml").unwrap();
        let points = f.points().into_iter().map(|p| (p, empty(), None));
        Group::by_settings(points)
            .into_iter()
            .map(|g| (g.name, g.members.into_iter().map(|m| m.label).collect()))
            .collect()
    };
    let seeds = |n: &[&str]| n.iter().map(|s| format!("seed={s}")).collect::<Vec<_>>();
    assert_eq!(
        grouped("seed = [1, 2]\nlr = [0.001, 0.002]"),
        [
            ("lr=0.001".to_string(), seeds(&["1", "2"])),
            ("lr=0.002".to_string(), seeds(&["1", "2"])),
        ]
    );
    assert_eq!(
        grouped("decoder = [\"slot_mixer\", \"transformer\"]"),
        [
            (
                "decoder=slot_mixer".to_string(),
                vec!["decoder=slot_mixer".to_string()]
            ),
            (
                "decoder=transformer".to_string(),
                vec!["decoder=transformer".to_string()]
            ),
        ]
    );
    assert_eq!(
        grouped("seed = [0, 1, 2]"),
        [("base".to_string(), seeds(&["0", "1", "2"]))]
    );
}

/// The report of a seed group: `groups.csv`, a section of `results.md`, the table and the
/// group's charts on the page, every link to a file that is there.
#[test]
fn the_report_shows_each_group_and_links_only_files_it_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let mut points = three_seeds(dir.path());
    let other = run(
        &dir.path().join("lr=0.002"),
        "lr=0.002",
        &[(10.0, 100, 20.0, Some(0.6)), (20.0, 200, 21.0, Some(0.7))],
    );
    points.push((
        Point {
            settings: vec![("lr".into(), "0.002".into())],
        },
        other,
        Some(result("x", 21.0, Some(0.7))),
    ));
    let rows: Vec<PointResult> = points.iter().filter_map(|p| p.2.clone()).collect();
    let curves: Vec<Curve> = points.iter().map(|p| p.1.clone()).collect();
    let targets = [Target {
        metric: Metric::FgAri,
        value: 0.5,
    }];
    let seeds = SeedReport::new(&Group::by_settings(points), &targets);
    let out = dir.path().join("report");
    let report = Report {
        title: "sweep lr".into(),
        note: "three seeds".into(),
        rows: &rows,
        curves: &curves,
        strips: Vec::new(),
        refresh_s: None,
    };
    let page = html::write_with_seeds(&out, &report, &seeds).unwrap();

    let csv = std::fs::read_to_string(out.join(html::GROUPS_CSV)).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 3, "{csv}");
    assert_eq!(
        lines[0],
        "group,seeds,members,test_fg_ari_mean,test_fg_ari_min,test_fg_ari_max,test_fg_ari_each,\
         test_psnr_mean,test_psnr_min,test_psnr_max,test_psnr_each,fg_ari>=0.5_reached,\
         fg_ari>=0.5_mean_s,fg_ari>=0.5_mean_step,fg_ari>=0.5_each_s,fg_ari>=0.5_each_step"
    );
    assert_eq!(
        lines[1],
        "lr=0.001,3,seed=0;seed=1;seed=2,0.850,0.800,0.900,0.800;0.900;,25.00,24.50,25.50,\
         24.50;25.50;,2,25.5,255,30.0;21.0;,300;210;"
    );
    assert_eq!(
        lines[2],
        "lr=0.002,1,lr=0.002,0.700,0.700,0.700,0.700,21.00,21.00,21.00,21.00,1,10.0,100,10.0,100"
    );

    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(
        md.contains("## Seed groups") && md.contains("min–max"),
        "{md}"
    );
    assert!(
        md.contains(
            "| lr=0.001 | 3: seed=0, seed=1, seed=2 | 0.850 (0.800–0.900) | 0.800 / 0.900 / n/a | \
             25.00 (24.50–25.50) | 24.50 / 25.50 / n/a | 25.5 (2/3) | \
             30.0 s @ step 300 / 21.0 s @ step 210 / never |"
        ),
        "{md}"
    );
    let results_csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    assert_eq!(
        results_csv.lines().count(),
        4,
        "results.csv stays one row per point"
    );

    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("<h2>Seed groups</h2>") && html.contains("25.5 (2/3)"));
    // A chart per metric of the group with seeds, one of every group's mean; none for
    // the group of one.
    for f in [
        "group-0-fg_ari.png",
        "group-0-psnr.svg",
        "groups-fg_ari.png",
        "groups-psnr.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
        assert!(
            html.contains(&f.replace(".svg", ".png")),
            "{f} not on the page"
        );
    }
    assert!(!out.join("group-1-psnr.png").exists());
    let svg = std::fs::read_to_string(out.join("group-0-fg_ari.svg")).unwrap();
    assert!(
        svg.contains("lr=0.001 (mean of 3)") && svg.contains("target 0.5"),
        "{svg}"
    );
    for link in html
        .split("src=\"")
        .skip(1)
        .chain(html.split("href=\"").skip(1))
    {
        let target = &link[..link.find('"').unwrap()];
        assert!(out.join(target).exists(), "{target} linked but not written");
    }
}

/// Groups of one (a sweep without seeds) get the table but no charts of their own.
#[test]
fn groups_of_one_draw_no_group_charts() {
    let dir = tempfile::tempdir().unwrap();
    let c = run(dir.path(), "decoder=x", &[(10.0, 1, 20.0, Some(0.5))]);
    let groups = Group::by_name([(
        "decoder=x".to_string(),
        Member {
            label: "decoder=x".into(),
            curve: c.clone(),
            result: None,
        },
    )]);
    let seeds = SeedReport::new(&groups, &[]);
    assert!(!seeds.has_seeds());
    let out = dir.path().join("r");
    let report = Report {
        title: "t".into(),
        note: String::new(),
        rows: &[],
        curves: &[c],
        strips: Vec::new(),
        refresh_s: None,
    };
    let page = html::write_with_seeds(&out, &report, &seeds).unwrap();
    let html = std::fs::read_to_string(page).unwrap();
    assert!(html.contains("<h2>Seed groups</h2>") && !html.contains("group-0-"));
    assert!(out.join(html::GROUPS_CSV).exists() && !out.join("results.md").exists());
}

/// TensorBoard gets one event per time of the grid, its step strictly increasing, with
/// each metric's mean, min and max where that metric has a point.
#[test]
fn tensorboard_events_carry_the_mean_curves_in_time_order() {
    use osrt_run::tensorboard::proto::summary::value::Value;
    let dir = tempfile::tempdir().unwrap();
    let groups = Group::by_settings(three_seeds(dir.path()));
    let g = &SeedReport::new(&groups, &[]).groups[0];
    let events = g.tensorboard_events();
    let times: Vec<f64> = events.iter().map(|e| e.1).collect();
    assert_eq!(times, [12.0, 20.0, 21.0, 22.0, 29.0]);
    assert!(events.windows(2).all(|w| w[0].0 < w[1].0), "steps increase");
    assert_eq!(events[0].0, 120);
    let first: Vec<(String, f32)> = events[0]
        .2
        .iter()
        .map(|v| match v.value {
            Some(Value::SimpleValue(x)) => (v.tag.clone(), x),
            _ => panic!("not a scalar"),
        })
        .collect();
    let tags: Vec<&str> = first.iter().map(|(t, _)| t.as_str()).collect();
    assert_eq!(
        tags,
        [
            "fg_ari/mean",
            "fg_ari/min",
            "fg_ari/max",
            "psnr/mean",
            "psnr/min",
            "psnr/max"
        ]
    );
    assert!(
        (first[0].1 - 0.22).abs() < 1e-6 && (first[2].1 - 0.32).abs() < 1e-6,
        "{first:?}"
    );
    assert_eq!(g.folder_name(), "lr=0.001");
}

/// The shipped time-to-quality sweep: four settings, three seeds each.
#[test]
fn the_time_to_quality_sweep_has_groups_of_three_seeds() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sweeps/time-to-quality.toml");
    let f = SweepFile::load(&path).unwrap();
    let groups = Group::by_settings(f.points().into_iter().map(|p| (p, empty(), None)));
    let got: Vec<(&str, Vec<&str>)> = groups
        .iter()
        .map(|g| {
            let labels = g.members.iter().map(|m| m.label.as_str()).collect();
            (g.name.as_str(), labels)
        })
        .collect();
    let seeds = vec!["seed=0", "seed=1", "seed=2"];
    assert_eq!(
        got,
        [
            ("horizon=fixed", seeds.clone()),
            ("horizon=budget", seeds.clone()),
            ("slot_gradient=bilevel", seeds.clone()),
            ("slot_gradient=implicit", seeds.clone()),
            ("precision=bf16", seeds),
        ]
    );
}
