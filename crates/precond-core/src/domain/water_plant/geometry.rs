//! The 2D geometry kit of the water-plant world: points, segments, rectangles and convex
//! polygons, shared by the domain's collision checker and the simulator.

use std::ops::{Add, Mul, Sub};

/// A point or vector in the plane (metres).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Vec2 {
    /// Horizontal component, positive to the right.
    pub x: f64,
    /// Vertical component, positive up.
    pub y: f64,
}

impl Vec2 {
    /// The vector `(x, y)`.
    pub const fn new(x: f64, y: f64) -> Self {
        Self { x, y }
    }

    /// Dot product.
    pub fn dot(self, o: Vec2) -> f64 {
        self.x * o.x + self.y * o.y
    }

    /// The z-component of the 3D cross product.
    pub fn cross(self, o: Vec2) -> f64 {
        self.x * o.y - self.y * o.x
    }

    /// Euclidean length.
    pub fn norm(self) -> f64 {
        self.x.hypot(self.y)
    }

    /// This vector rotated clockwise by `angle` radians.
    pub fn rotated_cw(self, angle: f64) -> Vec2 {
        let (s, c) = angle.sin_cos();
        Vec2::new(self.x * c + self.y * s, -self.x * s + self.y * c)
    }

    /// This vector rotated counter-clockwise by `angle` radians.
    pub fn rotated_ccw(self, angle: f64) -> Vec2 {
        self.rotated_cw(-angle)
    }
}

impl Add for Vec2 {
    type Output = Vec2;
    fn add(self, o: Vec2) -> Vec2 {
        Vec2::new(self.x + o.x, self.y + o.y)
    }
}

impl Sub for Vec2 {
    type Output = Vec2;
    fn sub(self, o: Vec2) -> Vec2 {
        Vec2::new(self.x - o.x, self.y - o.y)
    }
}

impl Mul<f64> for Vec2 {
    type Output = Vec2;
    fn mul(self, k: f64) -> Vec2 {
        Vec2::new(self.x * k, self.y * k)
    }
}

/// A line segment from `a` to `b`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    /// First end.
    pub a: Vec2,
    /// Second end.
    pub b: Vec2,
}

/// An axis-aligned rectangle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Lower-left corner.
    pub low: Vec2,
    /// Upper-right corner.
    pub high: Vec2,
}

impl Rect {
    /// The corners, counter-clockwise from the lower left.
    pub fn corners(&self) -> [Vec2; 4] {
        [
            self.low,
            Vec2::new(self.high.x, self.low.y),
            self.high,
            Vec2::new(self.low.x, self.high.y),
        ]
    }
}

/// Whether two convex polygons (vertices in order, either orientation) overlap, touching
/// included; a polygon of two vertices is a segment. Separating-axis test.
pub fn convex_overlap(p: &[Vec2], q: &[Vec2]) -> bool {
    fn separated_by_edges_of(p: &[Vec2], q: &[Vec2]) -> bool {
        let n = p.len();
        for i in 0..n {
            let e = p[(i + 1) % n] - p[i];
            let axis = Vec2::new(-e.y, e.x);
            if axis.x == 0.0 && axis.y == 0.0 {
                continue;
            }
            let (mut p_lo, mut p_hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for v in p {
                let d = axis.dot(*v);
                p_lo = p_lo.min(d);
                p_hi = p_hi.max(d);
            }
            let (mut q_lo, mut q_hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for v in q {
                let d = axis.dot(*v);
                q_lo = q_lo.min(d);
                q_hi = q_hi.max(d);
            }
            if p_hi < q_lo || q_hi < p_lo {
                return true;
            }
        }
        false
    }
    !(separated_by_edges_of(p, q) || separated_by_edges_of(q, p))
}

/// The convex hull of `points` (counter-clockwise, Andrew's monotone chain). Sorts `points`.
pub fn convex_hull(points: &mut [Vec2]) -> Vec<Vec2> {
    points.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    if points.len() < 3 {
        return points.to_vec();
    }
    // Whether `p` turns counter-clockwise after the hull's last two points.
    let turns_left = |hull: &[Vec2], p: Vec2| {
        let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
        (b - a).cross(p - a) > 0.0
    };
    let mut hull: Vec<Vec2> = Vec::with_capacity(2 * points.len());
    // Lower hull, left to right.
    for &p in points.iter() {
        while hull.len() >= 2 && !turns_left(&hull, p) {
            hull.pop();
        }
        hull.push(p);
    }
    // Upper hull, right to left.
    let lower = hull.len() + 1;
    for &p in points.iter().rev().skip(1) {
        while hull.len() >= lower && !turns_left(&hull, p) {
            hull.pop();
        }
        hull.push(p);
    }
    hull.pop();
    hull
}
