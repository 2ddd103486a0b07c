//! A mobile base on uneven ground: the true dynamics of the `base` world.
//!
//! The robot's model says a base moves by exactly the commanded displacement. The base drives
//! the displacement in small increments, and where it is decides what each increment does:
//! - on a **slippery slope** (a rotated rectangle), the wheels slip: each increment is turned by
//!   [`BaseParams::slip_angle`] and shortened by [`BaseParams::slip_scale`] — short moves there
//!   stay within tolerance, long ones do not;
//! - in a **crosswind corridor**, every increment is pushed sideways by a share of its length;
//! - a **hidden box** (the model does not know it) stops the base where it meets it;
//! - the arena's walls stop it (as the model's clipping does).
//!
//! Deterministic.

/// An axis-aligned rectangle, `[x0, x1] × [y0, y1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Area {
    /// Lower-left corner.
    pub low: [f64; 2],
    /// Upper-right corner.
    pub high: [f64; 2],
}

impl Area {
    fn contains(&self, p: [f64; 2]) -> bool {
        (0..2).all(|i| p[i] >= self.low[i] && p[i] <= self.high[i])
    }
}

/// Where the ground misbehaves.
#[derive(Debug, Clone, PartialEq)]
pub struct BaseParams {
    /// The slope's centre.
    pub slip_centre: [f64; 2],
    /// The slope's half extents along its own axes.
    pub slip_half: [f64; 2],
    /// The slope's rotation (rad).
    pub slip_rotation: f64,
    /// How far each increment turns on the slope (rad).
    pub slip_angle: f64,
    /// The share of each increment kept on the slope.
    pub slip_scale: f64,
    /// The crosswind corridor.
    pub wind: Area,
    /// Sideways push per unit of path driven in the corridor (`x`, `y`).
    pub wind_push: [f64; 2],
    /// The hidden box.
    pub hidden_box: Area,
    /// The arena.
    pub arena: Area,
    /// Increments per action.
    pub substeps: usize,
}

impl Default for BaseParams {
    /// A unit arena with a slope left of centre, a crosswind corridor across the top-right and
    /// a box below right.
    fn default() -> Self {
        Self {
            slip_centre: [0.3, 0.42],
            slip_half: [0.26, 0.16],
            slip_rotation: 0.6,
            slip_angle: 0.7,
            slip_scale: 0.8,
            wind: Area {
                low: [0.4, 0.68],
                high: [1.0, 0.9],
            },
            wind_push: [0.0, -0.35],
            hidden_box: Area {
                low: [0.58, 0.18],
                high: [0.8, 0.45],
            },
            arena: Area {
                low: [0.0, 0.0],
                high: [1.0, 1.0],
            },
            substeps: 20,
        }
    }
}

/// The base (see the module docs).
#[derive(Debug, Clone)]
pub struct BaseSim {
    p: BaseParams,
}

impl BaseSim {
    /// The base on `params`' ground.
    pub fn new(params: BaseParams) -> Self {
        Self { p: params }
    }

    /// Its parameters.
    pub fn params(&self) -> &BaseParams {
        &self.p
    }

    /// Whether `p` lies on the slope.
    pub fn on_slope(&self, p: [f64; 2]) -> bool {
        let (s, c) = self.p.slip_rotation.sin_cos();
        let d = [p[0] - self.p.slip_centre[0], p[1] - self.p.slip_centre[1]];
        let local = [c * d[0] + s * d[1], -s * d[0] + c * d[1]];
        local[0].abs() <= self.p.slip_half[0] && local[1].abs() <= self.p.slip_half[1]
    }

    /// Whether `p` lies inside the hidden box.
    pub fn blocked(&self, p: [f64; 2]) -> bool {
        self.p.hidden_box.contains(p)
    }

    /// Where the base ends after driving `a` from `s`. Non-finite inputs leave it in place.
    pub fn step(&self, s: &[f64], a: &[f64]) -> Vec<f64> {
        if s.len() != 2 || a.len() != 2 || s.iter().chain(a).any(|x| !x.is_finite()) {
            return s.to_vec();
        }
        let n = self.p.substeps.max(1);
        let inc = [a[0] / n as f64, a[1] / n as f64];
        let len = inc[0].hypot(inc[1]);
        let mut p = [s[0], s[1]];
        for _ in 0..n {
            let mut d = inc;
            if self.on_slope(p) {
                let (sn, cs) = self.p.slip_angle.sin_cos();
                d = [
                    self.p.slip_scale * (cs * d[0] - sn * d[1]),
                    self.p.slip_scale * (sn * d[0] + cs * d[1]),
                ];
            }
            if self.p.wind.contains(p) {
                d[0] += self.p.wind_push[0] * len;
                d[1] += self.p.wind_push[1] * len;
            }
            let next = [
                (p[0] + d[0]).clamp(self.p.arena.low[0], self.p.arena.high[0]),
                (p[1] + d[1]).clamp(self.p.arena.low[1], self.p.arena.high[1]),
            ];
            if self.blocked(next) {
                break;
            }
            p = next;
        }
        p.to_vec()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::euclidean as dist;

    #[test]
    fn open_ground_is_exact_and_the_slope_punishes_long_moves_only() {
        let base = BaseSim::new(BaseParams::default());
        let s = [0.1, 0.9];
        assert!(dist(&base.step(&s, &[0.08, 0.0]), &[0.18, 0.9]) < 1e-12);
        let on = [0.3, 0.45];
        assert!(base.on_slope(on));
        let long = base.step(&on, &[0.1, 0.0]);
        let short = base.step(&on, &[0.02, 0.0]);
        assert!(dist(&long, &[0.4, 0.45]) > 0.05, "{long:?}");
        assert!(dist(&short, &[0.32, 0.45]) < 0.02, "{short:?}");
    }

    #[test]
    fn the_box_stops_and_the_wind_pushes() {
        let base = BaseSim::new(BaseParams::default());
        let stopped = base.step(&[0.55, 0.3], &[0.1, 0.0]);
        assert!(stopped[0] < 0.6 && stopped[0] > 0.55, "{stopped:?}");
        let pushed = base.step(&[0.6, 0.8], &[0.1, 0.0]);
        assert!(pushed[1] < 0.78, "{pushed:?}");
    }
}
