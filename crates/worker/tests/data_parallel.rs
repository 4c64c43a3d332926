//! Data-parallel equivalence over the real gRPC ring: 2 workers × batch B/2 take the same
//! step as 1 worker × batch B (up to float reduction order), and the two replicas stay
//! bit-identical.

use candle_core::Device;
use osrt_collective::{Mailbox, Ring, RingConfig, serve};
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    BatchConfig, InputSelection, Scene, TargetViews, build_batch, generator::generate_scene,
};
use osrt_proto::auth::Token;
use osrt_proto::credentials::Credentials;
use osrt_trainer::distributed::Signals;
use osrt_trainer::{JobConfig, Trainer};
use osrt_worker::reduce::reduce;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Duration;

fn scenes(n: u64) -> Vec<Scene> {
    let cfg = GeneratorConfig {
        image_size: 8,
        antialias: 1,
        ..GeneratorConfig::clevr_lite()
    };
    (0..n)
        .map(|i| generate_scene(&cfg, 5, "train", i).unwrap())
        .collect()
}

/// A ring of two ranks over real gRPC on loopback.
async fn rings(job: &str, bucket_floats: usize, chunk_floats: usize) -> Vec<Ring> {
    let token = Token::generate();
    let mut addrs = Vec::new();
    let mut boxes = Vec::new();
    for _ in 0..2 {
        let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        addrs.push(format!("http://{}", l.local_addr().unwrap()));
        let m = Mailbox::new(job);
        tokio::spawn(serve(
            l,
            m.clone(),
            Credentials::new(token.clone(), None),
            std::future::pending(),
        ));
        boxes.push(m);
    }
    (0..2)
        .map(|rank| {
            Ring::new(
                RingConfig {
                    job: job.into(),
                    generation: 1,
                    first_step: 0,
                    rank,
                    peers: addrs.clone(),
                    bucket_floats,
                    chunk_floats,
                    timeout: Duration::from_secs(10),
                    credentials: Credentials::new(token.clone(), None),
                },
                boxes[rank].clone(),
            )
            .unwrap()
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_half_batches_step_like_one_full_batch() {
    let job = JobConfig::preset("tiny").unwrap();
    let data = scenes(16);
    let mut rings = rings("eq", 5000, 1000).await;
    let mut single = Trainer::new(job.clone(), Device::Cpu).unwrap();
    let mut r0 = Trainer::new(job.clone(), Device::Cpu).unwrap();
    let mut r1 = Trainer::new(job, Device::Cpu).unwrap();
    let cfg = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::All,
        rays_per_scene: Some(32),
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    // Uneven shares (3 + 1 scenes) check the weighting by real sample counts.
    for (step, share) in [(0u64, 2usize), (1, 3), (2, 1), (3, 2)] {
        let refs: Vec<&Scene> = data[step as usize * 3..step as usize * 3 + 4]
            .iter()
            .collect();
        let full = build_batch(&refs, &cfg, &mut ChaCha8Rng::seed_from_u64(step)).unwrap();
        let rng = || ChaCha8Rng::seed_from_u64(100 + step);
        let g = single.gradients(&full, &mut rng()).unwrap();
        let one = reduce(None, &mut None, step + 1, 0, g, Signals::default())
            .await
            .unwrap();
        single.apply(one.loss, one.grads).unwrap();

        let g0 = r0.gradients(&full.slice(0..share), &mut rng()).unwrap();
        let g1 = r1.gradients(&full.slice(share..4), &mut rng()).unwrap();
        let (ring0, ring1) = rings.split_at_mut(1);
        let (mut none0, mut none1) = (None, None);
        let (a, b) = tokio::join!(
            reduce(
                Some(&mut ring0[0]),
                &mut none0,
                step + 1,
                0,
                g0,
                Signals::default()
            ),
            reduce(
                Some(&mut ring1[0]),
                &mut none1,
                step + 1,
                1,
                g1,
                Signals::default()
            ),
        );
        let (a, b) = (a.unwrap(), b.unwrap());
        assert_eq!(a.samples, 4.0);
        assert_eq!(
            a.grads.host(),
            b.grads.host(),
            "both ranks hold the same averaged bytes"
        );
        assert!((a.loss - one.loss).abs() < 1e-6 * one.loss.abs().max(1.0));
        r0.apply(a.loss, a.grads).unwrap();
        r1.apply(b.loss, b.grads).unwrap();
    }
    // Rank 1 computes a NaN: the reduced gradient is not finite on both ranks, and both
    // learn that rank 1 produced it.
    let refs: Vec<&Scene> = data[..4].iter().collect();
    let full = build_batch(&refs, &cfg, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    let g0 = r0
        .gradients(&full.slice(0..2), &mut ChaCha8Rng::seed_from_u64(9))
        .unwrap();
    let mut g1 = r1
        .gradients(&full.slice(2..4), &mut ChaCha8Rng::seed_from_u64(9))
        .unwrap();
    g1.grads[5] = f32::NAN;
    let (ring0, ring1) = rings.split_at_mut(1);
    let (mut none0, mut none1) = (None, None);
    let (a, b) = tokio::join!(
        reduce(
            Some(&mut ring0[0]),
            &mut none0,
            5,
            0,
            g0,
            Signals::default()
        ),
        reduce(
            Some(&mut ring1[0]),
            &mut none1,
            5,
            1,
            g1,
            Signals::default()
        ),
    );
    for r in [a.unwrap(), b.unwrap()] {
        assert!(r.grads.host().unwrap()[5].is_nan());
        assert_eq!(r.nonfinite.only, Some(1));
        assert_eq!(r.nonfinite.to_string(), "rank 1");
    }
    let (p, p0, p1) = (
        single.params.flatten().unwrap(),
        r0.params.flatten().unwrap(),
        r1.params.flatten().unwrap(),
    );
    assert_eq!(p0, p1, "replicas are bit-identical");
    let max_diff = p
        .iter()
        .zip(&p0)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(max_diff < 1e-4, "2 × B/2 vs 1 × B: max |Δθ| = {max_diff}");
    let moved = p
        .iter()
        .zip(
            Trainer::new(JobConfig::preset("tiny").unwrap(), Device::Cpu)
                .unwrap()
                .params
                .flatten()
                .unwrap(),
        )
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        moved > 1e-3,
        "the steps changed the weights (max move {moved})"
    );
}

fn random(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-1e3f32..1e3)).collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// A gradient on a device (here a CPU tensor, which takes the same path as a GPU's but
/// for the page-locked memory) staged through the ring bucket by bucket reduces to the
/// bits the host path gives, with the same loss, scene count, signals and non-finite
/// ranks, on both ranks, step after step with the staging kept; also where the control
/// values straddle buckets (4-float buckets: one of control values only, one of both).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_staged_device_gradient_reduces_to_the_host_paths_bits() {
    use osrt_trainer::{Gradient, StepGradients};
    for (bucket, params) in [(4usize, 1003usize), (5000, 40_001)] {
        let mut host_rings = rings("host", bucket, 1000).await;
        let mut staged_rings = rings("staged", bucket, 1000).await;
        let mut staging = [None, None];
        for step in 0..3u64 {
            let mut grads = [random(params, 2 * step), random(params, 2 * step + 1)];
            if step == 2 {
                grads[1][params / 2] = f32::NAN;
            }
            let signals = Signals {
                evaluate: step == 1,
                stop: step == 2,
                horizon: (step == 1).then_some(16_000_001),
            };
            let g = |rank: usize, device: bool| StepGradients {
                loss: 0.25 + rank as f64 + step as f64,
                grads: if device {
                    let v = grads[rank].clone();
                    Gradient::Device(
                        candle_core::Tensor::from_vec(v, params, &Device::Cpu).unwrap(),
                    )
                } else {
                    Gradient::Host(grads[rank].clone())
                },
                samples: 1 + rank + step as usize,
                phases: None,
            };
            let (h0, h1) = host_rings.split_at_mut(1);
            let (mut none0, mut none1) = (None, None);
            let (a, b) = tokio::join!(
                reduce(Some(&mut h0[0]), &mut none0, step, 0, g(0, false), signals),
                reduce(Some(&mut h1[0]), &mut none1, step, 1, g(1, false), signals),
            );
            let host = [a.unwrap(), b.unwrap()];
            let (s0, s1) = staged_rings.split_at_mut(1);
            let (st0, st1) = staging.split_at_mut(1);
            let (a, b) = tokio::join!(
                reduce(Some(&mut s0[0]), &mut st0[0], step, 0, g(0, true), signals),
                reduce(Some(&mut s1[0]), &mut st1[0], step, 1, g(1, true), signals),
            );
            let staged = [a.unwrap(), b.unwrap()];
            for (h, s) in host.iter().zip(&staged) {
                // On a GPU the reduced gradient is a tensor there; on the CPU the
                // staging's host buffer.
                let sg = match &s.grads {
                    Gradient::Device(t) => t.to_vec1::<f32>().unwrap(),
                    Gradient::Host(v) => v.clone(),
                };
                let differs = (bits(&sg).iter().zip(bits(h.grads.host().unwrap())))
                    .position(|(a, b)| *a != b);
                assert_eq!(
                    differs, None,
                    "bucket {bucket} step {step}: first differing float"
                );
                assert_eq!(s.loss.to_bits(), h.loss.to_bits());
                assert_eq!(s.samples, h.samples);
                assert_eq!(s.signals, h.signals);
                assert_eq!(s.nonfinite, h.nonfinite);
            }
            assert_eq!(staged[0].samples, (3 + 2 * step) as f64);
            assert_eq!(staged[1].signals, signals, "rank 0's signals reach rank 1");
            let want_bad = if step == 2 { Some(1) } else { None };
            assert_eq!(staged[0].nonfinite.only, want_bad);
        }
    }
}

/// The trainer's copy of the ring's cut into buckets is the ring's.
#[test]
fn the_stagings_buckets_are_the_rings() {
    for (len, bucket) in [(1009, 4), (40_007, 5000), (16, 16), (17, 16), (1, 1 << 22)] {
        let ring = osrt_collective::Layout::new(len, 2, bucket, 1000).buckets;
        assert_eq!(osrt_trainer::staging::ring_buckets(len, bucket), ring);
    }
}
