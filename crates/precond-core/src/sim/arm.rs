//! A planar arm in a vertical plane, under gravity: the true dynamics of the `arm` world.
//!
//! `n` uniform rods hang from a fixed shoulder at the origin; joint `k`'s angle is relative to
//! the link before it (link 0's to the horizontal `+x` axis). An action asks the joints to move
//! by `Δq`: the arm's PD controller tracks the target `q + Δq` (clipped to the joint limits, as
//! the robot's kinematic model assumes) for [`ArmParams::horizon`] seconds from rest, with
//! torques clipped to each actuator's limit and **no gravity compensation**, so
//! - away from contact the arm ends where the model says up to a *sag* `≈ G(q) / K_p` that
//!   varies smoothly with the configuration (small with the links near vertical, large when
//!   stretched out horizontally);
//! - where gravity needs more torque than an actuator has, the joint falls;
//! - links that meet the obstacles (a shelf, the floor) stop on them: a stiff penalty contact
//!   at the link ends and middles.
//!
//! The dynamics are the rigid-body equations `M(q) q̈ + c(q, q̇) + G(q) = τ + Jᵀ F_contact − b q̇`
//! with the mass matrix and gravity from the links' Jacobians, the velocity terms from the mass
//! matrix's derivatives (Christoffel form, derivatives by central differences), integrated by
//! semi-implicit Euler. The world is deterministic (no episode variation).

/// An axis-aligned rectangle of the arm's plane, `[x0, x1] × [y0, y1]` (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Lower-left corner.
    pub low: [f64; 2],
    /// Upper-right corner.
    pub high: [f64; 2],
}

impl Rect {
    /// The penetration of `p` and the outward normal of the nearest face, if `p` is inside.
    fn penetration(&self, p: [f64; 2]) -> Option<(f64, [f64; 2])> {
        let inside = (0..2).all(|i| p[i] > self.low[i] && p[i] < self.high[i]);
        if !inside {
            return None;
        }
        let faces = [
            (p[0] - self.low[0], [-1.0, 0.0]),
            (self.high[0] - p[0], [1.0, 0.0]),
            (p[1] - self.low[1], [0.0, -1.0]),
            (self.high[1] - p[1], [0.0, 1.0]),
        ];
        faces.into_iter().min_by(|a, b| a.0.total_cmp(&b.0))
    }
}

/// The arm's build and controller.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmParams {
    /// Link lengths (m), shoulder first; also fixes the number of joints.
    pub lengths: Vec<f64>,
    /// Link masses (kg), uniform rods.
    pub masses: Vec<f64>,
    /// Proportional gains (N m / rad).
    pub kp: Vec<f64>,
    /// Derivative gains (N m s / rad).
    pub kd: Vec<f64>,
    /// Actuator torque limits (N m).
    pub torque_limit: Vec<f64>,
    /// Joint limits, lower (rad); stiff stops hold the joints inside.
    pub joint_low: Vec<f64>,
    /// Joint limits, upper (rad).
    pub joint_high: Vec<f64>,
    /// Viscous friction of every joint (N m s / rad).
    pub damping: f64,
    /// Gravity (m / s², pointing to `−y`).
    pub gravity: f64,
    /// Seconds the controller tracks one action's target.
    pub horizon: f64,
    /// Integration step (s).
    pub dt: f64,
    /// Obstacles in the arm's plane.
    pub obstacles: Vec<Rect>,
    /// Contact stiffness (N / m) and damping (N s / m) of the obstacles.
    pub contact: (f64, f64),
}

impl Default for ArmParams {
    /// A three-link arm (0.4, 0.35, 0.25 m) whose shoulder cannot hold the arm stretched out
    /// horizontally, above a floor at `y = −0.05 m`, beside a shelf at `x ∈ [0.2, 0.5] m`,
    /// `y ∈ [0.45, 0.55] m`.
    fn default() -> Self {
        Self {
            lengths: vec![0.4, 0.35, 0.25],
            masses: vec![2.0, 1.5, 0.8],
            kp: vec![400.0, 200.0, 80.0],
            kd: vec![30.0, 12.0, 3.0],
            torque_limit: vec![20.0, 10.0, 4.0],
            joint_low: vec![0.0, -2.0, -2.0],
            joint_high: vec![std::f64::consts::PI, 2.0, 2.0],
            damping: 0.5,
            gravity: 9.81,
            horizon: 0.5,
            dt: 0.002,
            obstacles: vec![
                Rect {
                    low: [-2.0, -2.0],
                    high: [2.0, -0.05],
                },
                Rect {
                    low: [0.2, 0.45],
                    high: [0.5, 0.55],
                },
            ],
            contact: (4000.0, 40.0),
        }
    }
}

/// The arm (see the module docs).
#[derive(Debug, Clone)]
pub struct ArmSim {
    p: ArmParams,
}

/// The most links an arm may have (the dynamics run on fixed-size matrices, unused joints
/// padded with an identity mass).
pub const MAX_LINKS: usize = 4;

type Mat = nalgebra::Matrix4<f64>;
type Vec4 = nalgebra::Vector4<f64>;

/// Points per link checked for contact (its end, its middle).
const CONTACT_POINTS: [f64; 2] = [0.5, 1.0];

/// The link angles and their sines and cosines at one configuration.
struct Pose {
    n: usize,
    cos: [f64; MAX_LINKS],
    sin: [f64; MAX_LINKS],
}

impl Pose {
    fn new(q: &[f64]) -> Self {
        let mut p = Self {
            n: q.len(),
            cos: [0.0; MAX_LINKS],
            sin: [0.0; MAX_LINKS],
        };
        let mut phi = 0.0;
        for (i, x) in q.iter().enumerate() {
            phi += x;
            (p.sin[i], p.cos[i]) = phi.sin_cos();
        }
        p
    }
}

impl ArmSim {
    /// The arm with `params` (at most [`MAX_LINKS`] links; extra links are ignored).
    pub fn new(mut params: ArmParams) -> Self {
        params.lengths.truncate(MAX_LINKS);
        Self { p: params }
    }

    /// Its parameters.
    pub fn params(&self) -> &ArmParams {
        &self.p
    }

    fn n(&self) -> usize {
        self.p.lengths.len()
    }

    /// The point at fraction `u` along link `i`, and its Jacobian's columns.
    fn point(&self, pose: &Pose, i: usize, u: f64) -> ([f64; 2], [[f64; 2]; MAX_LINKS]) {
        let l = &self.p.lengths;
        let mut p = [0.0, 0.0];
        for (j, lj) in l.iter().enumerate().take(i) {
            p[0] += lj * pose.cos[j];
            p[1] += lj * pose.sin[j];
        }
        p[0] += u * l[i] * pose.cos[i];
        p[1] += u * l[i] * pose.sin[i];
        // Column k: the lever from joint k to the point, turned by 90°.
        let mut jac = [[0.0; 2]; MAX_LINKS];
        let mut acc = [u * l[i] * pose.cos[i], u * l[i] * pose.sin[i]];
        for k in (0..=i).rev() {
            jac[k] = [-acc[1], acc[0]];
            if k > 0 {
                acc[0] += l[k - 1] * pose.cos[k - 1];
                acc[1] += l[k - 1] * pose.sin[k - 1];
            }
        }
        (p, jac)
    }

    /// The mass matrix `M(q)`, its derivatives `∂M/∂q_k` and the gravity torques `G(q)`.
    fn dynamics(&self, pose: &Pose) -> (Mat, [Mat; MAX_LINKS], Vec4) {
        let n = pose.n;
        let mut m = Mat::identity();
        for a in 0..n {
            m[(a, a)] = 0.0;
        }
        let mut dm = [Mat::zeros(); MAX_LINKS];
        let mut g = Vec4::zeros();
        for i in 0..n {
            let (mi, li) = (self.p.masses[i], self.p.lengths[i]);
            let (_, jc) = self.point(pose, i, 0.5);
            // ∂(column c)/∂q_k = −(the position lever from joint max(c, k) to the point).
            let lever = |from: usize| -> [f64; 2] {
                let mut v = [0.5 * li * pose.cos[i], 0.5 * li * pose.sin[i]];
                for j in from..i {
                    v[0] += self.p.lengths[j] * pose.cos[j];
                    v[1] += self.p.lengths[j] * pose.sin[j];
                }
                v
            };
            let inertia = mi * li * li / 12.0;
            for a in 0..=i {
                for b in 0..=i {
                    m[(a, b)] += mi * (jc[a][0] * jc[b][0] + jc[a][1] * jc[b][1]) + inertia;
                }
                g[a] += mi * self.p.gravity * jc[a][1];
            }
            for (k, dmk) in dm.iter_mut().enumerate().take(i + 1) {
                for a in 0..=i {
                    let da = lever(a.max(k));
                    for b in 0..=i {
                        let db = lever(b.max(k));
                        dmk[(a, b)] -= mi
                            * (da[0] * jc[b][0]
                                + da[1] * jc[b][1]
                                + jc[a][0] * db[0]
                                + jc[a][1] * db[1]);
                    }
                }
            }
        }
        (m, dm, g)
    }

    /// Joint torques of the contacts (and of the joint stops) at `q` moving at `qd`.
    fn contact_torques(&self, q: &[f64], pose: &Pose, qd: &Vec4) -> Vec4 {
        let n = self.n();
        let (k, d) = self.p.contact;
        let mut tau = Vec4::zeros();
        for i in 0..n {
            for &u in &CONTACT_POINTS {
                let (p, jac) = self.point(pose, i, u);
                for o in &self.p.obstacles {
                    let Some((depth, normal)) = o.penetration(p) else {
                        continue;
                    };
                    let v_n: f64 = (0..n)
                        .map(|c| (jac[c][0] * normal[0] + jac[c][1] * normal[1]) * qd[c])
                        .sum();
                    // Push out, damp only the approach (no sticking).
                    let f = (k * depth - d * v_n.min(0.0)).max(0.0);
                    for (c, jc) in jac.iter().enumerate().take(n) {
                        tau[c] += f * (jc[0] * normal[0] + jc[1] * normal[1]);
                    }
                }
            }
        }
        // Joint stops: stiff springs beyond the limits.
        for j in 0..n {
            let (lo, hi) = (self.p.joint_low[j], self.p.joint_high[j]);
            if q[j] < lo {
                tau[j] += 500.0 * (lo - q[j]) - 5.0 * qd[j].min(0.0);
            } else if q[j] > hi {
                tau[j] -= 500.0 * (q[j] - hi) + 5.0 * qd[j].max(0.0);
            }
        }
        tau
    }

    /// Whether any checked point of the arm at `q` lies inside an obstacle.
    pub fn in_contact(&self, q: &[f64]) -> bool {
        let pose = Pose::new(&q[..self.n().min(q.len())]);
        (0..pose.n).any(|i| {
            CONTACT_POINTS.iter().any(|&u| {
                let (p, _) = self.point(&pose, i, u);
                self.p.obstacles.iter().any(|o| o.penetration(p).is_some())
            })
        })
    }

    /// Where the arm ends after tracking `q + a` (clipped to the joint limits) from rest at `q`
    /// for the horizon, held inside the joint limits. Non-finite inputs leave the arm where it
    /// is.
    pub fn step(&self, q: &[f64], a: &[f64]) -> Vec<f64> {
        let n = self.n();
        if q.len() != n || a.len() != n || q.iter().chain(a).any(|x| !x.is_finite()) {
            return q.to_vec();
        }
        let target: Vec<f64> = (0..n)
            .map(|j| (q[j] + a[j]).clamp(self.p.joint_low[j], self.p.joint_high[j]))
            .collect();
        let mut q = q.to_vec();
        let mut qd = Vec4::zeros();
        let steps = (self.p.horizon / self.p.dt).round().max(1.0) as usize;
        for _ in 0..steps {
            let pose = Pose::new(&q);
            let (m, dm, g) = self.dynamics(&pose);
            let mut tau = Vec4::zeros();
            for j in 0..n {
                let u: f64 = self.p.kp[j] * (target[j] - q[j]) - self.p.kd[j] * qd[j];
                tau[j] = u.clamp(-self.p.torque_limit[j], self.p.torque_limit[j]);
            }
            tau -= self.p.damping * qd;
            tau += self.contact_torques(&q, &pose, &qd);
            tau -= g;
            // c(q, q̇) = Ṁ q̇ − ½ ∇_q (q̇ᵀ M q̇).
            for (k, dmk) in dm.iter().enumerate().take(n) {
                tau -= dmk * qd * qd[k];
                tau[k] += 0.5 * qd.dot(&(dmk * qd));
            }
            let Some(chol) = m.cholesky() else {
                break;
            };
            let qdd = chol.solve(&tau);
            qd += qdd * self.p.dt;
            for j in 0..n {
                q[j] += qd[j] * self.p.dt;
            }
            if q.iter().any(|x| !x.is_finite()) {
                break;
            }
        }
        for (j, x) in q.iter_mut().enumerate() {
            *x = x.clamp(self.p.joint_low[j], self.p.joint_high[j]);
        }
        q
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn free_arm() -> ArmSim {
        ArmSim::new(ArmParams {
            obstacles: Vec::new(),
            ..ArmParams::default()
        })
    }

    #[test]
    fn an_upright_arm_goes_where_it_is_told() {
        // Links straight up: gravity has no lever arm, so the PD target is reached.
        let arm = free_arm();
        let q = [std::f64::consts::FRAC_PI_2, 0.0, 0.0];
        let next = arm.step(&q, &[0.05, 0.0, 0.0]);
        let err: f64 = next
            .iter()
            .zip([q[0] + 0.05, 0.0, 0.0])
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(err < 0.03, "{next:?}");
    }

    #[test]
    fn a_stretched_out_arm_sags_under_gravity() {
        let arm = free_arm();
        let q = [0.3, 0.0, 0.0];
        let next = arm.step(&q, &[0.0, 0.0, 0.0]);
        assert!(next[0] < q[0] - 0.05, "the shoulder sags: {next:?}");
    }

    #[test]
    fn the_shelf_stops_the_arm() {
        let mut shelf_only = ArmParams::default();
        shelf_only.obstacles.remove(0);
        let arm = ArmSim::new(shelf_only);
        let free = free_arm();
        // A configuration clear of everything whose free motion ends inside the shelf.
        let mut found = None;
        'search: for i in 0..14 {
            for j in 0..9 {
                let q = [0.2 + 0.1 * i as f64, -1.0 + 0.25 * j as f64, 0.0];
                for a in [[0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, -0.25, 0.0]] {
                    if !arm.in_contact(&q) && arm.in_contact(&free.step(&q, &a)) {
                        found = Some((q, a));
                        break 'search;
                    }
                }
            }
        }
        let (q, a) = found.expect("some motion runs into the shelf");
        let (unblocked, blocked) = (free.step(&q, &a), arm.step(&q, &a));
        let d: f64 = unblocked
            .iter()
            .zip(&blocked)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(
            d > 0.05,
            "{q:?} + {a:?}: free {unblocked:?} blocked {blocked:?}"
        );
    }

    #[test]
    fn the_mass_matrix_is_symmetric_positive_and_energy_consistent() {
        let arm = free_arm();
        let q = [0.7, -0.4, 0.9];
        let (m, dm, g) = arm.dynamics(&Pose::new(&q));
        assert!((m - m.transpose()).abs().max() < 1e-12);
        assert!(m.cholesky().is_some());
        // Gravity is the gradient of the potential energy; ∂M/∂q_k the mass matrix's.
        let potential = |q: &[f64]| -> f64 {
            (0..3)
                .map(|i| arm.p.masses[i] * arm.p.gravity * arm.point(&Pose::new(q), i, 0.5).0[1])
                .sum()
        };
        for k in 0..3 {
            let mut a = q.to_vec();
            let mut b = q.to_vec();
            a[k] += 1e-6;
            b[k] -= 1e-6;
            let fd = (potential(&a) - potential(&b)) / 2e-6;
            assert!((fd - g[k]).abs() < 1e-5, "joint {k}: {fd} vs {}", g[k]);
            let dm_fd = (arm.dynamics(&Pose::new(&a)).0 - arm.dynamics(&Pose::new(&b)).0) / 2e-6;
            assert!(
                (dm_fd - dm[k]).abs().max() < 1e-5,
                "joint {k}: {dm_fd} vs {}",
                dm[k]
            );
        }
    }
}
