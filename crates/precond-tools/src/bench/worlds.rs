//! `precond bench worlds`: what each continuous world asks of a learner, before any learning —
//! the share of state-actions truly within `d_max`, the simulator's cost per step, and on
//! random problems what the oracle (a planner over the true precondition) and the baseline
//! (the model's own plan, no precondition) achieve, open and closed loop; with margins, what a
//! *cautious* oracle achieves that trusts only moves whose true deviation is below `m · d_max`
//! — how many problems need steps close to `d_max`, which a learner that must be confident
//! cannot trust.

use crate::experiment::reference;
use precond_core::domain::{Domain, LocalModel};
use precond_core::sim::ContinuousWorld;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// Prints the figures of every continuous world: `samples` uniform state-actions, `problems`
/// random problems, reference plans of `max_extensions`; then, for each of `margins`, the
/// share of state-actions within `m · d_max` and the cautious oracle's figures.
pub fn run(samples: usize, problems: usize, max_extensions: u32, margins: &[f64]) {
    println!(
        "continuous worlds: {samples} uniform state-actions, {problems} problems, reference plans of {max_extensions} extensions (the oracle's: twice that)"
    );
    println!(
        "{:<8} {:>6} {:>10} {:>9} {:>8} {:>8} {:>8} {:>9} {:>9}",
        "world", "d_max", "within", "µs/step", "oracle", "open", "closed", "baseline", "s"
    );
    for world in [
        ContinuousWorld::arm(),
        ContinuousWorld::base(),
        ContinuousWorld::pusher(),
    ] {
        let domain = world.domain();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut within = 0;
        let mut within_margin = vec![0usize; margins.len()];
        let mut n = 0;
        let t0 = Instant::now();
        while n < samples {
            let s = domain.sample_state(&mut rng);
            if !world.possible(&s) {
                continue;
            }
            let a = domain.sample_action(&s, &mut rng);
            let d = domain.distance(&domain.predict(&s, &a), &world.step(&s, &a));
            within += usize::from(d < world.d_max());
            for (w, m) in within_margin.iter_mut().zip(margins) {
                *w += usize::from(d < m * world.d_max());
            }
            n += 1;
        }
        let per_step = t0.elapsed().as_secs_f64() * 1e6 / samples.max(1) as f64;
        let t0 = Instant::now();
        let (mut solvable, mut open, mut closed, mut baseline) = (0, 0, 0, 0);
        let mut cautious = vec![(0usize, 0usize, 0usize); margins.len()];
        for k in 0..problems {
            let problem = world.sample_problem(&domain, &mut rng);
            for (c, m) in cautious.iter_mut().zip(margins) {
                let o = reference::oracle(
                    &world,
                    &domain,
                    &problem,
                    m * world.d_max(),
                    max_extensions,
                    k as u64,
                );
                c.0 += usize::from(o.solvable);
                c.1 += usize::from(o.open_loop);
                c.2 += usize::from(o.closed_loop);
            }
            let r = reference::continuous(&world, &domain, &problem, max_extensions, k as u64);
            solvable += usize::from(r.oracle_solvable);
            open += usize::from(r.oracle_open_loop);
            closed += usize::from(r.oracle_closed_loop);
            baseline += usize::from(r.baseline);
        }
        let share = |k: usize| k as f64 / problems.max(1) as f64;
        println!(
            "{:<8} {:>6} {:>10.2} {:>9.1} {:>8.2} {:>8.2} {:>8.2} {:>9.2} {:>9.1}",
            world.name(),
            world.d_max(),
            within as f64 / samples.max(1) as f64,
            per_step,
            share(solvable),
            share(open),
            share(closed),
            share(baseline),
            t0.elapsed().as_secs_f64()
        );
        for ((m, w), (c_solvable, c_open, c_closed)) in
            margins.iter().zip(&within_margin).zip(&cautious)
        {
            println!(
                "{:<8} {:>6} {:>10.2} {:>9} {:>8.2} {:>8.2} {:>8.2}",
                format!("  ×{m}"),
                m * world.d_max(),
                *w as f64 / samples.max(1) as f64,
                "",
                share(*c_solvable),
                share(*c_open),
                share(*c_closed),
            );
        }
    }
    println!(
        "within: share of state-actions whose true deviation is below d_max; oracle: problems the \
         oracle finds a plan for; open / closed: the oracle's plans executed open / closed loop \
         reach the goal; baseline: the model's own plan executed open loop reaches it; ×m: \
         the same for a cautious oracle that trusts only moves whose true deviation is below \
         m · d_max (closed loop still replans beyond d_max)"
    );
}
