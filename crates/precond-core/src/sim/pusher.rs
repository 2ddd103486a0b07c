//! A puck pushed across a floor: the true dynamics of the `pusher` world.
//!
//! The robot's model says the puck ends exactly where it is pushed to. The pusher drives the
//! puck at constant speed for [`PusherParams::push_seconds`] (`v = a / T`), then lets go, and the
//! puck slides on, slowed by Coulomb friction `μ(x, y) g`:
//! - on dry floor (`μ` large) the slide after release is a few millimetres;
//! - on a **wet patch** (`μ` falls smoothly towards its centre) it slides `v² / (2 μ g)` further:
//!   slow, short pushes stay within tolerance, fast ones overshoot — a deviation that grows
//!   smoothly with the push and the place;
//! - a **post** and the arena's **walls** stop a pushed puck and bounce a sliding one
//!   (restitution [`PusherParams::restitution`]) — sharp deviations.
//!
//! Semi-implicit Euler at [`PusherParams::dt`]; deterministic.

/// The floor, the obstacles and the push.
#[derive(Debug, Clone, PartialEq)]
pub struct PusherParams {
    /// Friction coefficient of the dry floor.
    pub mu_dry: f64,
    /// Friction coefficient at the wet patch's centre.
    pub mu_wet: f64,
    /// The wet patch's centre.
    pub wet_centre: [f64; 2],
    /// Radius within which the floor is fully wet.
    pub wet_inner: f64,
    /// Radius beyond which it is dry (the friction ramps smoothly in between).
    pub wet_outer: f64,
    /// The post's centre (for the puck's centre: the post's radius includes the puck's).
    pub post_centre: [f64; 2],
    /// The post's radius plus the puck's.
    pub post_radius: f64,
    /// The arena of the puck's centre, `[0, side]²`.
    pub side: f64,
    /// Share of the normal speed kept in a bounce.
    pub restitution: f64,
    /// Seconds of pushing per action.
    pub push_seconds: f64,
    /// Gravity (m / s²).
    pub gravity: f64,
    /// Integration step (s).
    pub dt: f64,
}

impl Default for PusherParams {
    /// A unit arena, a wet patch left of centre, a post right of centre.
    fn default() -> Self {
        Self {
            mu_dry: 0.6,
            mu_wet: 0.03,
            wet_centre: [0.4, 0.4],
            wet_inner: 0.2,
            wet_outer: 0.4,
            post_centre: [0.75, 0.65],
            post_radius: 0.1,
            side: 1.0,
            restitution: 0.4,
            push_seconds: 0.4,
            gravity: 9.81,
            dt: 0.002,
        }
    }
}

/// The puck (see the module docs).
#[derive(Debug, Clone)]
pub struct PusherSim {
    p: PusherParams,
}

impl PusherSim {
    /// The puck on `params`' floor.
    pub fn new(params: PusherParams) -> Self {
        Self { p: params }
    }

    /// Its parameters.
    pub fn params(&self) -> &PusherParams {
        &self.p
    }

    /// The floor's friction coefficient at `p`.
    pub fn mu(&self, p: [f64; 2]) -> f64 {
        let r = (p[0] - self.p.wet_centre[0]).hypot(p[1] - self.p.wet_centre[1]);
        let t = ((r - self.p.wet_inner) / (self.p.wet_outer - self.p.wet_inner)).clamp(0.0, 1.0);
        let smooth = t * t * (3.0 - 2.0 * t);
        self.p.mu_wet + (self.p.mu_dry - self.p.mu_wet) * smooth
    }

    /// Whether the puck's centre at `p` would overlap the post.
    pub fn in_post(&self, p: [f64; 2]) -> bool {
        (p[0] - self.p.post_centre[0]).hypot(p[1] - self.p.post_centre[1]) < self.p.post_radius
    }

    /// Resolves contact of the puck at `p` moving at `v` with the walls and the post: the
    /// position is put back on the surface and the normal velocity reflected by `bounce` (0:
    /// stopped along the normal).
    fn collide(&self, p: &mut [f64; 2], v: &mut [f64; 2], bounce: f64) {
        for (x, vx) in p.iter_mut().zip(v.iter_mut()) {
            if *x < 0.0 {
                *x = 0.0;
                if *vx < 0.0 {
                    *vx *= -bounce;
                }
            } else if *x > self.p.side {
                *x = self.p.side;
                if *vx > 0.0 {
                    *vx *= -bounce;
                }
            }
        }
        let d = [p[0] - self.p.post_centre[0], p[1] - self.p.post_centre[1]];
        let r = d[0].hypot(d[1]);
        if r < self.p.post_radius && r > 0.0 {
            let n = [d[0] / r, d[1] / r];
            p[0] = self.p.post_centre[0] + n[0] * self.p.post_radius;
            p[1] = self.p.post_centre[1] + n[1] * self.p.post_radius;
            let vn = v[0] * n[0] + v[1] * n[1];
            if vn < 0.0 {
                v[0] -= (1.0 + bounce) * vn * n[0];
                v[1] -= (1.0 + bounce) * vn * n[1];
            }
        }
    }

    /// Where the puck ends after a push of `a` from `s`. Non-finite inputs leave it in place.
    pub fn step(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        if s.len() != 2 || a.len() != 2 || s.iter().chain(a).any(|x| !x.is_finite()) {
            return s.to_vec();
        }
        let t_push = self.p.push_seconds.max(self.p.dt);
        let mut p = [s[0], s[1]];
        let mut v = [a[0] / t_push, a[1] / t_push];
        // Pushed: the pusher carries the puck; an obstacle stops it along its normal.
        let push_steps = (t_push / self.p.dt).round() as usize;
        for _ in 0..push_steps {
            let mut push = v;
            p[0] += push[0] * self.p.dt;
            p[1] += push[1] * self.p.dt;
            self.collide(&mut p, &mut push, 0.0);
        }
        // Released: it slides until friction stops it (at most 10 s).
        let max_steps = (10.0 / self.p.dt) as usize;
        for _ in 0..max_steps {
            let speed = v[0].hypot(v[1]);
            if speed < 1e-9 {
                break;
            }
            let decel = self.mu(p) * self.p.gravity * self.p.dt;
            if decel >= speed {
                break;
            }
            let k = (speed - decel) / speed;
            v = [v[0] * k, v[1] * k];
            p[0] += v[0] * self.p.dt;
            p[1] += v[1] * self.p.dt;
            self.collide(&mut p, &mut v, self.p.restitution);
        }
        p.to_vec()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::euclidean as dist;

    #[test]
    fn dry_floor_is_nearly_exact_and_the_wet_patch_overshoots_fast_pushes() {
        let sim = PusherSim::new(PusherParams::default());
        let dry = [0.1, 0.9];
        assert!(dist(&sim.step(&dry, &[0.1, 0.0]), &[0.2, 0.9]) < 0.01);
        let wet = [0.35, 0.35];
        let fast = sim.step(&wet, &[0.1, 0.0]);
        let slow = sim.step(&wet, &[0.02, 0.0]);
        assert!(dist(&fast, &[0.45, 0.35]) > 0.05, "{fast:?}");
        assert!(dist(&slow, &[0.37, 0.35]) < 0.01, "{slow:?}");
    }

    #[test]
    fn the_post_and_the_walls_stop_the_puck() {
        let sim = PusherSim::new(PusherParams::default());
        // Pushed straight at the post's centre: it stops on the post's surface.
        let [cx, cy] = sim.params().post_centre;
        let r = sim.params().post_radius;
        let stopped = sim.step(&[cx - r - 0.08, cy], &[0.12, 0.0]);
        assert!(!sim.in_post([stopped[0], stopped[1]]));
        assert!(stopped[0] < cx - r + 1e-6, "{stopped:?}");
        let wall = sim.step(&[0.97, 0.1], &[0.08, 0.0]);
        assert!(wall[0] <= 1.0);
    }
}
