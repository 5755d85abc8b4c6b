//! The farm coordinator's splatting of one training unit, timed: a 1920x1080 unit of one
//! sample a pixel arrives as 64-pixel tiles, each prepared ([`SplatPlan::prepare`]: film
//! positions drawn, interior gathered) and put in place (its samples near its edges copied,
//! its interior kept apart), then the bands gathered ([`UnitSplat::finish`]) and the unit
//! merged into an iteration's film. Prints the median
//! of the repetitions per step, in milliseconds, for the gaussian (Mitsuba's default) and
//! the tent filter.
//!
//! `cargo run --release -p pathfarm-render --example splat_unit [-- REPS [THREADS [FILTER]]]`

use std::time::Instant;

use glam::Vec3;
use pathfarm_render::filter::Filter;
use pathfarm_render::{Film, Region, RenderSettings, UnitSplat};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let mut args = std::env::args().skip(1);
    let reps: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(5);
    let threads: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(1);
    let only = args.next();
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global()
        .expect("one global pool");
    let (w, h) = (1920u32, 1080u32);
    let settings = RenderSettings::new(Some(1), None, 7);
    let tiles = Region::tiles(w, h, 64);
    let values: Vec<Vec<Vec3>> = (tiles.iter().enumerate())
        .map(|(t, r)| {
            (0..r.pixels())
                .map(|i| Vec3::new(i as f32 * 1e-3, t as f32 * 1e-2, 0.5))
                .collect()
        })
        .collect();
    let filters = [
        ("gaussian 0.5", Filter::Gaussian { stddev: 0.5 }),
        ("tent 1", Filter::Tent { radius: 1.0 }),
    ];
    println!(
        "1920x1080, 1 spp, {} tiles, {threads} thread(s), median of {reps} (ms)",
        tiles.len()
    );
    println!("| filter | prepare | put in place | bands | merge | total |");
    println!("|---|---|---|---|---|---|");
    for (name, filter) in filters {
        if only.as_deref().is_some_and(|o| !name.starts_with(o)) {
            continue;
        }
        let mut steps = [const { Vec::new() }; 4];
        let mut iteration = Film::new(w, h);
        // (buffers reused from unit to unit, as a session's spares are)
        let mut splat = UnitSplat::new(filter, (w, h), (&settings, 1), &[0]);
        let mut spare = None;
        for rep in 0..reps {
            if let Some(film) = spare.take() {
                splat.reuse((&settings, 1), &[rep as u64], film);
            }
            let plan = splat.plan().clone();
            let t0 = Instant::now();
            let prepared: Vec<_> = (tiles.iter().zip(&values))
                .map(|(&r, v)| plan.prepare(r, v))
                .collect();
            let t1 = Instant::now();
            for p in &prepared {
                splat.add_prepared(p);
            }
            let t2 = Instant::now();
            let film = splat.finish(&tiles);
            let t3 = Instant::now();
            film.merge_into(&mut iteration);
            let t4 = Instant::now();
            spare = Some(film.into_buffer());
            for (k, (a, b)) in [(t0, t1), (t1, t2), (t2, t3), (t3, t4)]
                .into_iter()
                .enumerate()
            {
                steps[k].push((b - a).as_secs_f64() * 1e3);
            }
        }
        let m: Vec<f64> = steps.into_iter().map(median).collect();
        let total: f64 = m.iter().sum();
        println!(
            "| {name} | {:.1} | {:.1} | {:.1} | {:.1} | {total:.1} |",
            m[0], m[1], m[2], m[3]
        );
        assert!(iteration.pixels[0].sum_w > 0.0, "the film was splatted");
    }
}
