//! The water plant's true dynamics: a 2D scene with swept collisions and water as particles.
//!
//! Geometry and units are the domain's ([`crate::domain::water_plant`]): metres, radians, water in
//! units. One step executes an action `[x, y, θ]` from a state:
//!
//! 1. **Translation** (when `x, y` change): the source, at its current tilt, moves along the
//!    straight segment to `(x, y)` and stops at the first contact with a leaf, the target
//!    container (a solid box), the pot or the stem. The swept area of a translated convex
//!    polygon is the convex hull of its start and end positions; the contact is found by
//!    bisection on that hull, to about a nanometre.
//! 2. **Rotation** (when `θ` changes): about the container's centre, in steps of at most
//!    [`WaterPlantSimParams::rotation_step`], stopping at the last free tilt before the first
//!    contact (refined by bisection). An action that both translates and rotates (which the
//!    domain rejects) is executed as the translation, then the rotation.
//!
//!    Obstacles the source already touches where it starts are ignored for that step, so that it
//!    can always move away from them.
//! 3. **Pour**: if the tilt it ends at is at least the pour angle, the source releases
//!    `min(volume, 1)` units from its lip as [`WaterPlantSimParams::particles`] particles of
//!    equal volume, each leaving the lip horizontally towards `+x` with a speed spread evenly
//!    over [`WaterPlantSimParams::stream_speed`] (a fan-shaped stream). A particle falls
//!    ballistically; when it hits a leaf it slides down along the leaf (over its following
//!    segments as long as they keep descending), drops off the end with a fraction
//!    [`WaterPlantSimParams::slide_retention`] of the free-fall speed gained while sliding, along
//!    the leaf's direction, and falls on. A particle that crosses the rim height strictly inside
//!    the opening lands in the target; every other one (including one released below the rim)
//!    is spilled. Particles interact only with the leaves and the opening.
//!
//! Volumes are conserved: with `P` poured and `k` of `N` particles in the target, the target
//! gains `P·k/N`, the spill `P − P·k/N`, the source loses `P`.
//!
//! **Episodes**: [`World::reset`] perturbs each nominal leaf: it turns about its attachment point
//! by a normal angle (s.d. [`WaterPlantSimParams::leaf_angle_sd`]) and slides along the stem by a
//! normal offset (s.d. [`WaterPlantSimParams::leaf_offset_sd`]), both clipped at two standard
//! deviations. A new simulator starts with the nominal leaves.

use super::World;
use crate::domain::DomainError;
use crate::domain::water_plant::{
    Leaf, MOTION_TOLERANCE, POUR_VOLUME, Pose, SPILLED, SRC_THETA, SRC_VOLUME, SRC_X, SRC_Y, Scene,
    TGT_VOLUME, Vec2, WaterPlant, convex_hull, convex_overlap,
};
use rand::RngCore;
use rand_distr::{Distribution, Normal};

/// Parameters of the simulator (the geometry comes from the domain).
#[derive(Debug, Clone, PartialEq)]
pub struct WaterPlantSimParams {
    /// Particles per pour (each carries `1/particles` of the poured volume). Default 100.
    pub particles: usize,
    /// Range of the particles' initial horizontal speed towards `+x` (m/s). Default
    /// `(0.05, 0.25)`: from 0.5 m above the rim the stream lands 1.6–8 cm right of the lip.
    pub stream_speed: (f64, f64),
    /// Gravitational acceleration (m/s²). Default 9.81.
    pub gravity: f64,
    /// Fraction of the speed `√(2 g Δh)` gained sliding down a leaf that a particle keeps when it
    /// drops off (friction). Default 0.3.
    pub slide_retention: f64,
    /// Largest tilt step of the rotation sweep before refinement (radians). Default 1°.
    pub rotation_step: f64,
    /// Standard deviation of a leaf's turn about its attachment per episode (radians).
    /// Default 0.04 (2.3°).
    pub leaf_angle_sd: f64,
    /// Standard deviation of a leaf's vertical shift along the stem per episode (m).
    /// Default 0.01.
    pub leaf_offset_sd: f64,
}

impl Default for WaterPlantSimParams {
    fn default() -> Self {
        Self {
            particles: 100,
            stream_speed: (0.05, 0.25),
            gravity: 9.81,
            slide_retention: 0.3,
            rotation_step: 1f64.to_radians(),
            leaf_angle_sd: 0.04,
            leaf_offset_sd: 0.01,
        }
    }
}

impl WaterPlantSimParams {
    /// Checks the parameters; errors name the field.
    pub fn check(&self) -> Result<(), DomainError> {
        if self.particles == 0 || self.particles > 100_000 {
            return Err(DomainError::new("particles: must be between 1 and 100000"));
        }
        let (lo, hi) = self.stream_speed;
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo <= hi) {
            return Err(DomainError::new(
                "stream_speed: need 0 ≤ low ≤ high, finite",
            ));
        }
        for (name, v, positive) in [
            ("gravity", self.gravity, true),
            ("rotation_step", self.rotation_step, true),
            ("slide_retention", self.slide_retention, false),
            ("leaf_angle_sd", self.leaf_angle_sd, false),
            ("leaf_offset_sd", self.leaf_offset_sd, false),
        ] {
            if !(v.is_finite() && (v > 0.0 || (!positive && v == 0.0))) {
                return Err(DomainError::new(format!(
                    "{name}: must be a {} finite number",
                    if positive { "positive" } else { "non-negative" }
                )));
            }
        }
        Ok(())
    }
}

/// Where the particles of one pour went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PourOutcome {
    /// Particles that entered the target.
    pub in_target: usize,
    /// Particles released.
    pub total: usize,
}

impl PourOutcome {
    /// Fraction of the poured water that entered the target.
    pub fn fraction_in_target(&self) -> f64 {
        self.in_target as f64 / self.total as f64
    }
}

/// The water-plant simulator (see the module docs).
#[derive(Debug, Clone)]
pub struct WaterPlantSim {
    domain: WaterPlant,
    params: WaterPlantSimParams,
    /// This episode's leaves.
    leaves: Vec<Leaf>,
    /// Everything the source can collide with, as convex polygons (boxes and leaf segments).
    obstacles: Vec<Vec<Vec2>>,
}

/// Most leaf contacts one particle can have before it is counted where it is.
const MAX_BOUNCES: usize = 16;

/// Bisection steps to locate a contact.
const BISECTION_STEPS: usize = 40;

/// Between `free` (not blocked) and `blocked`, the last value that is not, to
/// [`BISECTION_STEPS`] halvings of the interval.
fn last_free(mut free: f64, mut blocked: f64, is_blocked: impl Fn(f64) -> bool) -> f64 {
    for _ in 0..BISECTION_STEPS {
        let mid = 0.5 * (free + blocked);
        if is_blocked(mid) {
            blocked = mid;
        } else {
            free = mid;
        }
    }
    free
}

impl WaterPlantSim {
    /// A simulator for the domain's scene with the default parameters and the nominal leaves.
    pub fn new(domain: &WaterPlant) -> Self {
        Self::with_params(domain, WaterPlantSimParams::default())
            .expect("the default parameters are valid")
    }

    /// A simulator with the given parameters (checked) and the nominal leaves.
    pub fn with_params(
        domain: &WaterPlant,
        params: WaterPlantSimParams,
    ) -> Result<Self, DomainError> {
        params.check()?;
        let mut sim = Self {
            domain: domain.clone(),
            params,
            leaves: Vec::new(),
            obstacles: Vec::new(),
        };
        sim.set_leaves(domain.scene().leaves.clone());
        Ok(sim)
    }

    /// The parameters.
    pub fn params(&self) -> &WaterPlantSimParams {
        &self.params
    }

    /// The scene (from the domain; its leaves are the nominal ones).
    pub fn scene(&self) -> &Scene {
        self.domain.scene()
    }

    /// This episode's leaves (to draw them).
    pub fn leaves(&self) -> &[Leaf] {
        &self.leaves
    }

    /// Replaces this episode's leaves (for tests and custom scenes).
    pub fn set_leaves(&mut self, leaves: Vec<Leaf>) {
        let sc = self.domain.scene();
        let mut obstacles: Vec<Vec<Vec2>> =
            sc.fixed_obstacles().iter().map(|o| o.to_vec()).collect();
        for leaf in &leaves {
            obstacles.extend(leaf.segments().map(|s| vec![s.a, s.b]));
        }
        self.leaves = leaves;
        self.obstacles = obstacles;
    }

    /// Whether the source at `pose` touches anything (a leaf, the target, the pot or the stem).
    pub fn source_collides(&self, pose: Pose) -> bool {
        self.hits(&self.scene().source_corners(pose), &[])
    }

    /// Indices of the obstacles the polygon touches.
    fn touching(&self, poly: &[Vec2]) -> Vec<usize> {
        (0..self.obstacles.len())
            .filter(|&i| convex_overlap(poly, &self.obstacles[i]))
            .collect()
    }

    fn hits(&self, poly: &[Vec2], ignore: &[usize]) -> bool {
        self.obstacles
            .iter()
            .enumerate()
            .any(|(i, o)| !ignore.contains(&i) && convex_overlap(poly, o))
    }

    /// Moves the source from `from` towards `to` at its tilt; returns where it stops.
    pub fn translate(&self, from: Pose, to: Vec2) -> Pose {
        let sc = self.scene();
        let start = sc.source_corners(from);
        let ignore = self.touching(&start);
        let at = |t: f64| Pose {
            x: from.x + t * (to.x - from.x),
            y: from.y + t * (to.y - from.y),
            theta: from.theta,
        };
        let swept_hits = |t: f64| {
            let mut pts: Vec<Vec2> = start.to_vec();
            pts.extend(sc.source_corners(at(t)));
            self.hits(&convex_hull(&mut pts), &ignore)
        };
        if !swept_hits(1.0) {
            return Pose {
                x: to.x,
                y: to.y,
                theta: from.theta,
            };
        }
        at(last_free(0.0, 1.0, swept_hits))
    }

    /// Turns the source at `from` towards tilt `to`; returns where it stops.
    pub fn rotate(&self, from: Pose, to: f64) -> Pose {
        let sc = self.scene();
        let ignore = self.touching(&sc.source_corners(from));
        let at = |theta: f64| Pose { theta, ..from };
        let blocked_at = |theta: f64| self.hits(&sc.source_corners(at(theta)), &ignore);
        let n = ((to - from.theta).abs() / self.params.rotation_step)
            .ceil()
            .max(1.0) as usize;
        let mut prev = from.theta;
        for k in 1..=n {
            let theta = from.theta + (to - from.theta) * k as f64 / n as f64;
            if blocked_at(theta) {
                return at(last_free(prev, theta, blocked_at));
            }
            prev = theta;
        }
        at(to)
    }

    /// Releases the particles of a pour from `lip` and counts those that enter the target.
    pub fn pour(&self, lip: Vec2) -> PourOutcome {
        let n = self.params.particles;
        let (lo, hi) = self.params.stream_speed;
        let in_target = (0..n)
            .filter(|&i| {
                let u = lo + (hi - lo) * (i as f64 + 0.5) / n as f64;
                self.particle_enters_target(lip, Vec2::new(u, 0.0))
            })
            .count();
        PourOutcome {
            in_target,
            total: n,
        }
    }

    /// Follows one particle from `p` with velocity `v` until it crosses the rim height.
    pub fn particle_enters_target(&self, mut p: Vec2, mut v: Vec2) -> bool {
        let g = self.params.gravity;
        let (o_lo, o_hi, rim) = self.scene().opening();
        let mut left_leaf: Option<usize> = None;
        for _ in 0..MAX_BOUNCES {
            if p.y <= rim {
                return false;
            }
            // Time to fall to the rim height: p.y + v.y t − g t²/2 = rim (the later root).
            let t_rim = (v.y + (v.y * v.y + 2.0 * g * (p.y - rim)).sqrt()) / g;
            let mut first: Option<(f64, usize, usize)> = None;
            for (li, leaf) in self.leaves.iter().enumerate() {
                if Some(li) == left_leaf {
                    continue;
                }
                for (si, seg) in leaf.segments().enumerate() {
                    if let Some(t) = parabola_hits_segment(p, v, g, seg.a, seg.b)
                        && t < t_rim
                        && first.is_none_or(|(tb, _, _)| t < tb)
                    {
                        first = Some((t, li, si));
                    }
                }
            }
            match first {
                None => {
                    let x = p.x + v.x * t_rim;
                    return x > o_lo && x < o_hi;
                }
                Some((t, li, si)) => {
                    let hit = Vec2::new(p.x + v.x * t, p.y + v.y * t - 0.5 * g * t * t);
                    let (drop, dir) = slide_off(&self.leaves[li], si, hit, v.x);
                    let speed =
                        self.params.slide_retention * (2.0 * g * (hit.y - drop.y).max(0.0)).sqrt();
                    p = drop;
                    v = dir * speed;
                    left_leaf = Some(li);
                }
            }
        }
        false
    }

    /// Perturbs the nominal leaves for a new episode (see the module docs).
    fn perturbed_leaves(&self, rng: &mut dyn RngCore) -> Vec<Leaf> {
        let clipped_normal = |sd: f64, rng: &mut dyn RngCore| -> f64 {
            if sd == 0.0 {
                return 0.0;
            }
            let z: f64 = Normal::new(0.0, 1.0).expect("unit normal").sample(rng);
            sd * z.clamp(-2.0, 2.0)
        };
        self.scene()
            .leaves
            .iter()
            .map(|leaf| {
                let turn = clipped_normal(self.params.leaf_angle_sd, rng);
                let shift = clipped_normal(self.params.leaf_offset_sd, rng);
                let base = leaf.points[0];
                Leaf {
                    points: leaf
                        .points
                        .iter()
                        .map(|p| base + (*p - base).rotated_ccw(turn) + Vec2::new(0.0, shift))
                        .collect(),
                }
            })
            .collect()
    }
}

/// Earliest time `t > 0` at which the particle `p + v t + (0, −g t²/2)` crosses segment `a b`.
fn parabola_hits_segment(p: Vec2, v: Vec2, g: f64, a: Vec2, b: Vec2) -> Option<f64> {
    let d = b - a;
    let len2 = d.dot(d);
    if len2 == 0.0 {
        return None;
    }
    let n = Vec2::new(-d.y, d.x);
    // n · (p(t) − a) = c0 + c1 t + c2 t².
    let c0 = n.dot(p - a);
    let c1 = n.dot(v);
    let c2 = -0.5 * g * n.y;
    let mut roots = [f64::NAN; 2];
    if c2.abs() < 1e-15 {
        if c1.abs() > 1e-15 {
            roots[0] = -c0 / c1;
        }
    } else {
        let disc = c1 * c1 - 4.0 * c2 * c0;
        if disc < 0.0 {
            return None;
        }
        // Numerically stable quadratic roots.
        let sign = if c1 >= 0.0 { 1.0 } else { -1.0 };
        let q = -0.5 * (c1 + sign * disc.sqrt());
        roots[0] = q / c2;
        if q != 0.0 {
            roots[1] = c0 / q;
        }
    }
    let mut best: Option<f64> = None;
    for t in roots {
        if !(t.is_finite() && t > 1e-12) {
            continue;
        }
        let at = Vec2::new(p.x + v.x * t, p.y + v.y * t - 0.5 * g * t * t);
        let s = (at - a).dot(d) / len2;
        if (0.0..=1.0).contains(&s) && best.is_none_or(|b| t < b) {
            best = Some(t);
        }
    }
    best
}

/// Where a particle that hit segment `si` of `leaf` at `hit` drops off, and the unit direction it
/// leaves in: it slides downhill along the segment, and on along the polyline while the next
/// segment keeps descending. On a level segment it slides the way it was moving (`vx`).
fn slide_off(leaf: &Leaf, si: usize, hit: Vec2, vx: f64) -> (Vec2, Vec2) {
    let pts = &leaf.points;
    let (a, b) = (pts[si], pts[si + 1]);
    // Towards the tip (increasing index) or towards the stem.
    let towards_tip = if b.y != a.y {
        b.y < a.y
    } else {
        (b.x - a.x) * vx >= 0.0
    };
    let mut from = hit;
    let mut i = if towards_tip { si + 1 } else { si };
    loop {
        let to = pts[i];
        let dir = to - from;
        let next = if towards_tip {
            (i + 1 < pts.len()).then(|| i + 1)
        } else {
            i.checked_sub(1)
        };
        match next {
            Some(j) if pts[j].y < to.y => {
                from = to;
                i = j;
            }
            _ => {
                let len = dir.norm();
                let unit = if len > 0.0 {
                    dir * (1.0 / len)
                } else {
                    let e = if towards_tip { b - a } else { a - b };
                    e * (1.0 / e.norm())
                };
                return (to, unit);
            }
        }
    }
}

impl World for WaterPlantSim {
    /// Draws this episode's leaves from the nominal ones (see the module docs).
    fn reset(&mut self, rng: &mut dyn RngCore) {
        let leaves = self.perturbed_leaves(rng);
        self.set_leaves(leaves);
    }

    /// Executes `a = [x, y, θ]` from `s` (see the module docs).
    fn step(&mut self, s: &[f64], a: &[f64]) -> Vec<f64> {
        let mut pose = Pose::from_slice(s);
        if (a[0] - pose.x).hypot(a[1] - pose.y) > MOTION_TOLERANCE {
            pose = self.translate(pose, Vec2::new(a[0], a[1]));
        }
        if (a[2] - pose.theta).abs() > MOTION_TOLERANCE {
            pose = self.rotate(pose, a[2]);
        }
        let mut next = s.to_vec();
        next[SRC_X] = pose.x;
        next[SRC_Y] = pose.y;
        next[SRC_THETA] = pose.theta;
        let src = s[SRC_VOLUME];
        if pose.theta >= self.scene().pour_angle && src > 0.0 {
            let poured = src.min(POUR_VOLUME);
            let out = self.pour(self.scene().lip(pose));
            let gained = poured * out.in_target as f64 / out.total as f64;
            next[SRC_VOLUME] = src - poured;
            next[TGT_VOLUME] = s[TGT_VOLUME] + gained;
            next[SPILLED] = s[SPILLED] + (poured - gained);
        }
        next
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::water_plant::{Motion, TOTAL_WATER};
    use crate::domain::{Domain, LocalModel};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn setup() -> (WaterPlant, WaterPlantSim) {
        let d = WaterPlant::default();
        let w = WaterPlantSim::new(&d);
        (d, w)
    }

    fn pour_at(x: f64, y: f64) -> (Vec<f64>, Vec<f64>) {
        let d = WaterPlant::default();
        (d.start_state(x, y), vec![x, y, 135f64.to_radians()])
    }

    fn run(d: &WaterPlant, w: &mut WaterPlantSim, s: &[f64], a: &[f64]) -> (f64, Vec<f64>) {
        let next = w.step(s, a);
        (d.deviation(s, a, &next), next)
    }

    #[test]
    fn a_pour_below_the_leaves_over_the_target_succeeds() {
        let (d, mut w) = setup();
        for (x, y) in [(-0.05, 0.55), (0.05, 0.625), (-0.1, 0.75), (-0.15, 0.95)] {
            let (s, a) = pour_at(x, y);
            let (dev, next) = run(&d, &mut w, &s, &a);
            assert!(dev < d.default_d_max(), "({x}, {y}): {dev} {next:?}");
            assert!(d.is_goal(&next, &[1.0]), "({x}, {y}): {next:?}");
        }
    }

    #[test]
    fn a_pour_above_the_leaves_spills() {
        let (d, mut w) = setup();
        for (x, y) in [(0.0, 1.375), (-0.125, 1.7), (0.1, 1.1), (0.1, 1.05)] {
            let (s, a) = pour_at(x, y);
            // The model says it all goes in.
            assert_eq!(d.predict(&s, &a)[TGT_VOLUME], 1.0);
            let (dev, next) = run(&d, &mut w, &s, &a);
            assert!(dev > 0.4, "({x}, {y}): {dev} {next:?}");
            assert!(next[SPILLED] > 0.8, "({x}, {y}): {next:?}");
        }
    }

    #[test]
    fn a_pour_beside_the_target_spills_in_model_and_world() {
        let (d, mut w) = setup();
        for (x, y) in [(-0.625, 0.75), (-0.5, 1.25), (-0.75, 0.375)] {
            let (s, a) = pour_at(x, y);
            assert_eq!(d.predict(&s, &a)[SPILLED], 1.0);
            let (dev, next) = run(&d, &mut w, &s, &a);
            assert_eq!(next[SPILLED], 1.0);
            assert!(dev < 1e-12, "({x}, {y}): {dev}");
        }
    }

    #[test]
    fn without_leaves_pours_over_the_opening_succeed_at_any_height() {
        let (d, mut w) = setup();
        w.set_leaves(Vec::new());
        for y in [0.625, 1.0, 1.375] {
            let (s, a) = pour_at(-0.05, y);
            let (dev, next) = run(&d, &mut w, &s, &a);
            assert!(
                dev < d.default_d_max() && d.is_goal(&next, &[1.0]),
                "{y}: {next:?}"
            );
        }
    }

    #[test]
    fn a_translation_stops_on_a_leaf() {
        let (d, mut w) = setup();
        // Sideways into the lower leaf's tip.
        let s = d.start_state(-0.125, 0.9);
        let a = [0.2, 0.9, 0.0];
        let (dev, next) = run(&d, &mut w, &s, &a);
        assert!(next[SRC_X] < 0.0 && next[SRC_X] > -0.125, "{next:?}");
        assert_eq!(next[SRC_Y], 0.9);
        assert!(dev > d.default_d_max(), "{dev}");
        // Straight up under the lower leaf.
        let s = d.start_state(0.075, 0.70);
        let a = [0.075, 1.05, 0.0];
        let (dev, next) = run(&d, &mut w, &s, &a);
        assert!(next[SRC_Y] > 0.70 && next[SRC_Y] < 0.83, "{next:?}");
        assert!(dev > d.default_d_max(), "{dev}");
        // The model's collision checker lets both through.
        assert!(d.edge_allowed(&s, &a, &d.predict(&s, &a)));
    }

    #[test]
    fn a_translation_stops_at_the_target_container() {
        let (d, mut w) = setup();
        let s = d.start_state(-0.6, 0.275);
        let a = [-0.25, 0.275, 0.0];
        let next = w.step(&s, &a);
        // The source's right side touches the target's left wall at x = −0.20.
        assert!((next[SRC_X] + 0.06 - (-0.20)).abs() < 1e-6, "{next:?}");
        // From above, straight down onto the rim.
        let s = d.start_state(0.0, 0.6);
        let next = w.step(&s, &[0.0, 0.25, 0.0]);
        assert!((next[SRC_Y] - 0.10 - 0.30).abs() < 1e-6, "{next:?}");
    }

    #[test]
    fn a_translation_in_free_space_is_exact() {
        let (d, mut w) = setup();
        let s = d.start_state(-0.75, 0.5);
        let a = [-0.5, 0.75, 0.0];
        let (dev, next) = run(&d, &mut w, &s, &a);
        assert_eq!(&next[..3], &a);
        assert_eq!(dev, 0.0);
    }

    #[test]
    fn a_rotation_stops_at_contact_and_then_does_not_pour() {
        let (d, mut w) = setup();
        // Just under the lower leaf: the tilting container hits it before the pour angle.
        let (s, a) = pour_at(-0.1, 1.0);
        let (dev, next) = run(&d, &mut w, &s, &a);
        assert!(next[SRC_THETA] < d.scene().pour_angle, "{next:?}");
        assert_eq!(next[SRC_VOLUME], 1.0);
        assert!(dev > d.default_d_max());
        // Low over the rim: it hits the target container.
        let (s, a) = pour_at(0.0, 0.4075);
        let next = w.step(&s, &a);
        assert!(
            next[SRC_THETA] < d.scene().pour_angle && next[SRC_THETA] > 0.0,
            "{next:?}"
        );
    }

    #[test]
    fn an_action_that_both_translates_and_rotates_translates_then_rotates() {
        let (d, mut w) = setup();
        let s = d.start_state(-0.5, 0.625);
        let a = [-0.025, 0.625, 135f64.to_radians()];
        let next = w.step(&s, &a);
        assert_eq!(&next[..3], &a);
        assert!(d.is_goal(&next, &[1.0]));
    }

    #[test]
    fn water_is_conserved() {
        let (d, mut w) = setup();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        w.reset(&mut rng);
        for _ in 0..300 {
            let p = d.sample_problem(&mut rng);
            let mut s = p.start().to_vec();
            for _ in 0..4 {
                let a = if rand::Rng::random_bool(&mut rng, 0.5) {
                    d.sample_action(&s, &mut rng)
                } else {
                    let g = d.goal_target(&[1.0], &mut rng);
                    d.steer_toward(&s, &g, &mut rng)
                };
                s = w.step(&s, &a);
                let total = s[SRC_VOLUME] + s[TGT_VOLUME] + s[SPILLED];
                assert!((total - TOTAL_WATER).abs() < 1e-12, "{s:?}");
                assert!(s[SRC_VOLUME] >= 0.0 && s[TGT_VOLUME] >= 0.0 && s[SPILLED] >= 0.0);
            }
        }
    }

    #[test]
    fn leaves_move_between_episodes_but_stay_close() {
        let (d, mut w) = setup();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        w.reset(&mut rng);
        let first = w.leaves().to_vec();
        w.reset(&mut rng);
        let second = w.leaves().to_vec();
        assert_ne!(first, second);
        for leaves in [&first, &second] {
            for (leaf, nominal) in leaves.iter().zip(&d.scene().leaves) {
                for (p, q) in leaf.points.iter().zip(&nominal.points) {
                    // At most 2 s.d. of turn over the leaf's length plus 2 s.d. of shift.
                    assert!((*p - *q).norm() < 0.08, "{p:?} vs {q:?}");
                }
            }
        }
        // Same seed, same episode.
        let mut again = WaterPlantSim::new(&d);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        again.reset(&mut rng);
        assert_eq!(again.leaves(), &first[..]);
    }

    #[test]
    fn the_success_region_below_the_leaves_survives_leaf_noise() {
        let (d, mut w) = setup();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for _ in 0..20 {
            w.reset(&mut rng);
            let (s, a) = pour_at(-0.05, 0.575);
            let next = w.step(&s, &a);
            assert!(d.is_goal(&next, &[1.0]), "{next:?}");
            let (s, a) = pour_at(0.0, 1.4);
            let next = w.step(&s, &a);
            assert!(next[SPILLED] > 0.5, "{next:?}");
        }
    }

    #[test]
    fn water_sliding_down_a_leaf_leaves_at_its_low_end() {
        let (_, w) = setup();
        // On the lower leaf (rising to the left) water runs back to the stem and misses.
        assert!(!w.particle_enters_target(Vec2::new(0.075, 1.0), Vec2::new(0.0, 0.0)));
        // A particle in the clear falls straight in.
        assert!(w.particle_enters_target(Vec2::new(-0.075, 0.75), Vec2::new(0.0, 0.0)));
        // A lone leaf sloping down towards the opening's centre channels water into it.
        let mut w2 = w.clone();
        w2.set_leaves(vec![Leaf {
            points: vec![Vec2::new(0.5, 1.0), Vec2::new(0.0, 0.75)],
        }]);
        assert!(w2.particle_enters_target(Vec2::new(0.375, 1.25), Vec2::new(0.0, 0.0)));
        assert!(!w.particle_enters_target(Vec2::new(0.375, 1.25), Vec2::new(0.0, 0.0)));
    }

    #[test]
    fn the_model_is_right_where_nothing_is_in_the_way() {
        // Over a grid of pours and translations, the world agrees with the model (deviation
        // below d_max) everywhere the container and its water meet no leaf: beside the target
        // and below the leaves.
        let (d, mut w) = setup();
        w.set_leaves(Vec::new());
        let mut checked = 0;
        for i in 0..15 {
            for j in 0..10 {
                let x = -0.95 + 0.1 * i as f64;
                let y = 0.35 + 0.1 * j as f64;
                let s = d.start_state(x, y);
                for a in [vec![x, y, 2.36], vec![x + 0.25, y + 0.05, 0.0]] {
                    if !d.edge_allowed(&s, &a, &d.predict(&s, &a)) {
                        continue;
                    }
                    let lip = d.scene().lip(Pose::from_slice(&a));
                    let (lo, hi, _) = d.scene().opening();
                    // Within 10 cm of the opening's edges the stream's drift decides.
                    if a[2] > 2.0 && (lip.x - lo).abs().min((lip.x - hi).abs()) < 0.1 {
                        continue;
                    }
                    let next = w.step(&s, &a);
                    assert!(
                        d.deviation(&s, &a, &next) < d.default_d_max(),
                        "{a:?} {next:?}"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 150, "{checked}");
    }

    #[test]
    fn one_step_is_cheap() {
        let (d, mut w) = setup();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let start = std::time::Instant::now();
        let n = 200;
        for _ in 0..n {
            let s = d.sample_problem(&mut rng).start().to_vec();
            let g = d.goal_target(&[1.0], &mut rng);
            let a = d.steer_toward(&s, &g, &mut rng);
            let s2 = w.step(&s, &a);
            let _ = w.step(&s2, &[s2[0], s2[1], 2.4]);
        }
        let per_step = start.elapsed().as_secs_f64() / (2 * n) as f64;
        // Generous, for an unoptimised test build on a loaded machine.
        assert!(per_step < 5e-3, "{per_step}");
    }

    proptest::proptest! {
        #[test]
        fn a_step_ends_on_the_commanded_path_and_clear_of_everything(seed in 0u64..500) {
            let (d, mut w) = setup();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            w.reset(&mut rng);
            let mut s = d.sample_problem(&mut rng).start().to_vec();
            for _ in 0..4 {
                let a = d.sample_action(&s, &mut rng);
                let next = w.step(&s, &a);
                let pose = Pose::from_slice(&next);
                proptest::prop_assert!(!w.source_collides(pose), "{:?} -> {:?}", s, next);
                match d.motion(&s, &a) {
                    Motion::Translate => {
                        // On the segment from s to a, no further than a.
                        let (dx, dy) = (a[0] - s[0], a[1] - s[1]);
                        let t = ((next[0] - s[0]) * dx + (next[1] - s[1]) * dy) / (dx * dx + dy * dy);
                        let off = (next[0] - s[0] - t * dx).hypot(next[1] - s[1] - t * dy);
                        proptest::prop_assert!((-1e-9..=1.0 + 1e-9).contains(&t) && off < 1e-9);
                        proptest::prop_assert_eq!(next[SRC_THETA], s[SRC_THETA]);
                    }
                    Motion::Rotate => {
                        proptest::prop_assert_eq!(&next[..2], &s[..2]);
                        let (lo, hi) = if a[2] > s[2] { (s[2], a[2]) } else { (a[2], s[2]) };
                        proptest::prop_assert!(next[2] >= lo - 1e-12 && next[2] <= hi + 1e-12);
                    }
                    m => proptest::prop_assert!(false, "sample_action gave {:?}", m),
                }
                let total = next[SRC_VOLUME] + next[TGT_VOLUME] + next[SPILLED];
                proptest::prop_assert!((total - TOTAL_WATER).abs() < 1e-12);
                s = next;
            }
        }
    }

    #[test]
    fn rejects_bad_parameters() {
        let d = WaterPlant::default();
        for p in [
            WaterPlantSimParams {
                particles: 0,
                ..Default::default()
            },
            WaterPlantSimParams {
                stream_speed: (0.2, 0.1),
                ..Default::default()
            },
            WaterPlantSimParams {
                gravity: -1.0,
                ..Default::default()
            },
        ] {
            assert!(WaterPlantSim::with_params(&d, p).is_err());
        }
    }
}
