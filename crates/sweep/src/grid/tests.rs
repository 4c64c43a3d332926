/// A file that only adds points (or axis values, or comments) extends the earlier one;
/// one that changes a setting outside the points, or drops a point, does not.
#[test]
fn a_file_with_points_added_extends_the_earlier_one() {
    let f = |text: &str| super::SweepFile::parse(text, "test").unwrap();
    let earlier =
        f("name = \"s\"\nmax_minutes = 10.0\n[[points]]\nlr = 0.001\n[axes]\nseed = [0, 1]\n");
    let more = f(
        "# a comment\nname = \"s\"\nmax_minutes = 10.0\n[[points]]\nlr = 0.001\n[[points]]\nlr = 0.002\n[axes]\nseed = [0, 1, 2]\n",
    );
    assert!(more.extends(&earlier));
    assert!(earlier.extends(&earlier));
    assert!(!earlier.extends(&more), "points dropped");
    let longer =
        f("name = \"s\"\nmax_minutes = 20.0\n[[points]]\nlr = 0.001\n[axes]\nseed = [0, 1]\n");
    assert!(!longer.extends(&earlier), "another budget");
    let other =
        f("name = \"t\"\nmax_minutes = 10.0\n[[points]]\nlr = 0.001\n[axes]\nseed = [0, 1]\n");
    assert!(!other.extends(&earlier), "another name");
}

use super::*;

const FILE: &str = r#"
name = "demo"
preset = "tiny"
max_steps = 3
[axes]
decoder = ["slot_mixer", "transformer"]
slots = [3, 5]
targets = ["novel", "input"]
"#;

#[test]
fn points_are_the_product_in_axis_order() {
    let f = SweepFile::parse(FILE, "demo.toml").unwrap();
    let names: Vec<String> = f.points().iter().map(Point::name).collect();
    assert_eq!(names.len(), 8);
    assert_eq!(names[0], "decoder=slot_mixer,slots=3,targets=novel");
    assert_eq!(names[1], "decoder=slot_mixer,slots=3,targets=input");
    assert_eq!(names[7], "decoder=transformer,slots=5,targets=input");
}

/// A point may set the batch and its micro-batch (the same optimisation, another
/// memory); a micro-batch of 0 is refused with the point's name.
#[test]
fn a_point_sets_the_batch_and_its_micro_batch() {
    let f = SweepFile::parse(FILE, "demo.toml").unwrap();
    let base = f.base_job(Path::new(".")).unwrap();
    let point = |m: &str| Point {
        settings: vec![
            ("batch_size".into(), "8".into()),
            ("micro_batch_size".into(), m.into()),
        ],
    };
    let job = point("2").apply(&base).unwrap();
    assert_eq!(
        (job.train.batch_size, job.train.micro_batch_size),
        (8, Some(2))
    );
    let e = point("0").apply(&base).unwrap_err().to_string();
    assert!(e.contains("micro_batch_size"), "{e}");
}

#[test]
fn a_point_changes_exactly_its_settings() {
    let f = SweepFile::parse(FILE, "demo.toml").unwrap();
    let base = f.base_job(Path::new(".")).unwrap();
    let p = &f.points()[7];
    let job = p.apply(&base).unwrap();
    assert_eq!(job.model.slot_attention.num_slots, 5);
    assert_eq!(job.train.target_views, TargetViews::Input);
    assert!(matches!(
        job.model.decoder,
        osrt_model::decoder::Config::Transformer(_)
    ));
    assert_eq!(job.train, {
        let mut t = base.train.clone();
        t.target_views = TargetViews::Input;
        t
    });
}

#[test]
fn the_ray_input_axis_sets_the_encoder() {
    let f = SweepFile::parse(
        "name = \"x\"\npreset = \"tiny\"\nmax_steps = 1\n[axes]\nray_input = [\"concat\", \"add\", \"mul\"]\n",
        "x.toml",
    )
    .unwrap();
    let base = f.base_job(Path::new(".")).unwrap();
    let points = f.points();
    let got: Vec<_> = points[..2]
        .iter()
        .map(|p| p.apply(&base).unwrap().model.encoder.ray_input)
        .collect();
    use osrt_model::encoder::RayInput;
    assert_eq!(got, [RayInput::Concat, RayInput::Add]);
    let e = points[2].apply(&base).unwrap_err().to_string();
    assert!(
        e.contains("ray_input=mul") && e.contains("expected concat or add"),
        "{e}"
    );
}

#[test]
fn bad_files_and_points_say_what_is_wrong() {
    let no_budget = SweepFile::parse("name = \"x\"\n", "x.toml").unwrap_err();
    assert!(no_budget.to_string().contains("max_minutes or max_steps"));
    let typo = SweepFile::parse(
        "name = \"x\"\nmax_steps = 1\n[axes]\ndecoders = []\n",
        "x.toml",
    )
    .unwrap_err();
    assert!(typo.to_string().contains("decoders"), "{typo}");
    let f = SweepFile::parse(
        "name = \"x\"\npreset = \"tiny\"\nmax_steps = 1\n[axes]\ndecoder = [\"nerf\"]\ninput_views = [5]\n",
        "x.toml",
    )
    .unwrap();
    let base = f.base_job(Path::new(".")).unwrap();
    let e = f.check(&base, 3).unwrap_err().to_string();
    assert!(
        e.contains("decoder=nerf") && e.contains("unknown decoder"),
        "{e}"
    );
    let f = SweepFile::parse(
        "name = \"x\"\npreset = \"tiny\"\nmax_steps = 1\n[axes]\ninput_views = [1, 5]\n",
        "x.toml",
    )
    .unwrap();
    let e = f.check(&base, 3).unwrap_err().to_string();
    assert!(
        e.contains("input_views=5") && e.contains("only 3 views"),
        "{e}"
    );
}

/// Explicit points (rows of a table) come in file order, crossed with the axes; an
/// unknown setting, a point setting nothing and a setting the axes vary are refused.
#[test]
fn explicit_points_cross_the_axes() {
    let text = "name = \"t\"\npreset = \"tiny\"\nmax_steps = 1\n\
                [[points]]\ninput_views = 2\n\
                [[points]]\ndecoder = \"transformer\"\ninput_views = 1\n\
                [axes]\nseed = [0, 1]\n";
    let f = SweepFile::parse(text, "t.toml").unwrap();
    let names: Vec<String> = f.points().iter().map(Point::name).collect();
    assert_eq!(
        names,
        [
            "input_views=2,seed=0",
            "input_views=2,seed=1",
            "decoder=transformer,input_views=1,seed=0",
            "decoder=transformer,input_views=1,seed=1",
        ]
    );
    let base = JobConfig::preset("tiny").unwrap();
    let job = f.points()[2].apply(&base).unwrap();
    assert_eq!(job.train.input_views, 1);
    for (bad, want) in [
        ("[[points]]\nwidth = 3\n", "unknown setting `width`"),
        ("[[points]]\n", "sets nothing"),
        (
            "[[points]]\nseed = 3\n[axes]\nseed = [1]\n",
            "the axes vary too",
        ),
        ("[[points]]\nseed = [3]\n", "is not a value"),
    ] {
        let text = format!("name = \"t\"\nmax_steps = 1\n{bad}");
        let e = SweepFile::parse(&text, "t.toml").unwrap_err().to_string();
        assert!(e.contains(want), "{bad}: {e}");
    }
}

/// The shipped Table 4 sweep: its eight rows, each a valid job on 6-view scenes.
#[test]
fn the_table4_sweep_has_the_papers_rows() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/sweeps/table4.toml");
    let f = SweepFile::load(&path).unwrap();
    let base = f.base_job(path.parent().unwrap()).unwrap();
    let points = f.check(&base, 6).unwrap();
    let names: Vec<String> = points.iter().map(|(p, _)| p.name()).collect();
    assert_eq!(
        names,
        [
            "input_views=1",
            "input_views=3",
            "input_views=5",
            "decoder=spatial_broadcast,input_views=5",
            "decoder=transformer,input_views=5",
            "poses=unposed,input_views=5",
            "decoder=volumetric,input_views=5",
            "input_views=5,targets=input",
        ]
    );
    assert!(
        f.check(&base, 4).is_err(),
        "5 input views need more than 4 views"
    );
}

/// The shipped time-to-quality study: each change against the preset, three seeds
/// each, the changes made where they say.
#[test]
fn the_time_to_quality_sweep_changes_one_thing_per_point() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs/sweeps/time-to-quality.toml");
    let f = SweepFile::load(&path).unwrap();
    let base = f.base_job(path.parent().unwrap()).unwrap();
    let points = f.check(&base, 3).unwrap();
    let names: Vec<String> = points.iter().map(|(p, _)| p.name()).collect();
    let want: Vec<String> = [
        "horizon=fixed",
        "horizon=budget",
        "slot_gradient=bilevel",
        "slot_gradient=implicit",
        "precision=bf16",
    ]
    .iter()
    .flat_map(|c| (0..3).map(move |s| format!("{c},seed={s}")))
    .collect();
    assert_eq!(names, want);
    for (p, job) in &points {
        let seed: u64 = p.get("seed").unwrap().parse().unwrap();
        assert_eq!(job.train.seed, seed);
        let changed = (
            job.train.horizon != base.train.horizon,
            job.model.slot_attention.gradient != base.model.slot_attention.gradient,
            job.train.precision != base.train.precision,
        );
        let want = match (p.get("horizon"), p.get("slot_gradient"), p.get("precision")) {
            (Some("budget"), None, None) => (true, false, false),
            (Some("fixed"), None, None) => (false, false, false),
            (None, Some("bilevel" | "implicit"), None) => (false, true, false),
            (None, None, Some("bf16")) => (false, false, true),
            other => panic!("unexpected point {other:?}"),
        };
        assert_eq!(changed, want, "{}", p.name());
    }
}
