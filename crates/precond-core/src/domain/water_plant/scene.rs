//! The water-plant scene: the containers' geometry, the plant's leaves, the source's poses and
//! the bounds of the state and action spaces (see the parent module's docs for the layout).

use super::geometry::{Rect, Segment, Vec2};
use crate::domain::DomainError;
use std::f64::consts::PI;

/// A leaf: a polyline from where it grows out of the stem (`points[0]`) to its tip.
#[derive(Debug, Clone, PartialEq)]
pub struct Leaf {
    /// Vertices from the attachment point to the tip (at least two).
    pub points: Vec<Vec2>,
}

impl Leaf {
    /// The leaf's segments, from the attachment to the tip.
    pub fn segments(&self) -> impl Iterator<Item = Segment> + '_ {
        self.points.windows(2).map(|w| Segment { a: w[0], b: w[1] })
    }
}

/// A pose of the source container: the centre of its rectangle and its clockwise tilt.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Centre, horizontal (m).
    pub x: f64,
    /// Centre, vertical (m).
    pub y: f64,
    /// Tilt from upright, clockwise (towards `+x`), radians.
    pub theta: f64,
}

impl Pose {
    /// The source pose in a state, or the pose an action commands.
    pub fn from_slice(v: &[f64]) -> Self {
        Self {
            x: v[0],
            y: v[1],
            theta: v[2],
        }
    }

    /// The centre.
    pub fn position(&self) -> Vec2 {
        Vec2::new(self.x, self.y)
    }
}

/// The geometry of the scene and the limits of the source's motion (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Outer width of the source container (m).
    pub source_width: f64,
    /// Outer height of the source container (m).
    pub source_height: f64,
    /// The target container's outer box (m); its base centre is its pose.
    pub target: Rect,
    /// Thickness of the target's walls (m); the opening is the box's top minus the walls.
    pub target_wall: f64,
    /// The plant's pot.
    pub pot: Rect,
    /// The plant's stem.
    pub stem: Rect,
    /// The nominal leaves (the simulator perturbs them per episode).
    pub leaves: Vec<Leaf>,
    /// The tilt at and beyond which the source pours (radians; 130°).
    pub pour_angle: f64,
    /// Lower bounds of the source's pose `(x, y, θ)`.
    pub source_low: [f64; 3],
    /// Upper bounds of the source's pose `(x, y, θ)`.
    pub source_high: [f64; 3],
    /// Longest translation of one action (m), used by `steer` and `sample_action`.
    pub max_translation: f64,
    /// Region of the start positions of sampled problems: `(x_low, y_low)`.
    pub start_low: [f64; 2],
    /// Region of the start positions of sampled problems: `(x_high, y_high)`.
    pub start_high: [f64; 2],
}

impl Default for Scene {
    /// The documented default scene (metres, radians): a 12 × 20 cm jug, a 40 × 30 cm planter
    /// and a 1.25 m potted plant. It is large against `d_max = 0.1` on purpose: a translation
    /// that a leaf stops 10 cm short is clearly wrong, while the band of good pours below the
    /// leaves is several `d_max` wide.
    fn default() -> Self {
        Self {
            source_width: 0.12,
            source_height: 0.20,
            target: Rect {
                low: Vec2::new(-0.20, 0.0),
                high: Vec2::new(0.20, 0.30),
            },
            target_wall: 0.025,
            pot: Rect {
                low: Vec2::new(0.30, 0.0),
                high: Vec2::new(0.60, 0.25),
            },
            stem: Rect {
                low: Vec2::new(0.44, 0.25),
                high: Vec2::new(0.46, 1.25),
            },
            leaves: vec![
                // Lower leaf: rises from the stem to a tip over the opening's centre; water that
                // lands on it runs back to the stem.
                Leaf {
                    points: vec![
                        Vec2::new(0.45, 0.70),
                        Vec2::new(0.225, 0.85),
                        Vec2::new(0.0, 0.95),
                    ],
                },
                // Upper leaf: arches over the whole opening; its tip is left of the target.
                Leaf {
                    points: vec![
                        Vec2::new(0.45, 1.15),
                        Vec2::new(0.15, 1.25),
                        Vec2::new(-0.25, 1.10),
                    ],
                },
            ],
            pour_angle: 130f64.to_radians(),
            source_low: [-1.0, 0.25, 0.0],
            source_high: [0.75, 1.75, 150f64.to_radians()],
            max_translation: 0.35,
            start_low: [-0.85, 0.40],
            start_high: [-0.40, 1.10],
        }
    }
}

impl Scene {
    /// The source container's corners at `pose` (counter-clockwise from its lower left when
    /// upright; the lip is the third).
    pub fn source_corners(&self, pose: Pose) -> [Vec2; 4] {
        let (hw, hh) = (self.source_width / 2.0, self.source_height / 2.0);
        let c = pose.position();
        [
            Vec2::new(-hw, -hh),
            Vec2::new(hw, -hh),
            Vec2::new(hw, hh),
            Vec2::new(-hw, hh),
        ]
        .map(|v| c + v.rotated_cw(pose.theta))
    }

    /// Offset from the container's centre to its lip (the rim corner it pours over) at tilt
    /// `theta`. At 135° it is about `(+0.028, −0.113)`.
    pub fn lip_offset(&self, theta: f64) -> Vec2 {
        Vec2::new(self.source_width / 2.0, self.source_height / 2.0).rotated_cw(theta)
    }

    /// Where the water leaves the source at `pose`.
    pub fn lip(&self, pose: Pose) -> Vec2 {
        pose.position() + self.lip_offset(pose.theta)
    }

    /// Half the source's diagonal: the radius of the circle its rotation sweeps (m).
    pub fn source_radius(&self) -> f64 {
        0.5 * self.source_width.hypot(self.source_height)
    }

    /// The target's opening: `(x_low, x_high, rim_y)`; water crossing `y = rim_y` strictly
    /// between `x_low` and `x_high` enters the target.
    pub fn opening(&self) -> (f64, f64, f64) {
        (
            self.target.low.x + self.target_wall,
            self.target.high.x - self.target_wall,
            self.target.high.y,
        )
    }

    /// The model's rule: the lip is above the target's opening.
    pub fn above_opening(&self, lip: Vec2) -> bool {
        let (lo, hi, rim) = self.opening();
        lip.x > lo && lip.x < hi && lip.y > rim
    }

    /// The target container's pose `(x, y, θ)`: the centre of its base, upright.
    pub fn target_pose(&self) -> [f64; 3] {
        [
            0.5 * (self.target.low.x + self.target.high.x),
            self.target.low.y,
            0.0,
        ]
    }

    /// The fixed obstacles the collision checker knows: the target container (as a solid box),
    /// the pot and the stem, as polygons.
    pub fn fixed_obstacles(&self) -> [[Vec2; 4]; 3] {
        [
            self.target.corners(),
            self.pot.corners(),
            self.stem.corners(),
        ]
    }

    pub(super) fn check(&self) -> Result<(), DomainError> {
        let nums = [
            self.source_width,
            self.source_height,
            self.target_wall,
            self.pour_angle,
            self.max_translation,
        ];
        if nums.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(DomainError::new(
                "scene: sizes, wall, pour angle and max translation must be positive numbers",
            ));
        }
        for r in [self.target, self.pot, self.stem] {
            let c = [r.low.x, r.low.y, r.high.x, r.high.y];
            if c.iter().any(|v| !v.is_finite()) || r.low.x >= r.high.x || r.low.y >= r.high.y {
                return Err(DomainError::new(
                    "scene: every box needs finite corners with low < high",
                ));
            }
        }
        if 2.0 * self.target_wall >= self.target.high.x - self.target.low.x {
            return Err(DomainError::new(
                "scene: the target's walls leave no opening",
            ));
        }
        for (i, leaf) in self.leaves.iter().enumerate() {
            if leaf.points.len() < 2
                || leaf
                    .points
                    .iter()
                    .any(|p| !(p.x.is_finite() && p.y.is_finite()))
            {
                return Err(DomainError::new(format!(
                    "scene: leaf {i} needs at least two finite points"
                )));
            }
        }
        for i in 0..3 {
            let (lo, hi) = (self.source_low[i], self.source_high[i]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(DomainError::new(format!(
                    "scene: source pose bound {i} must be finite with low < high"
                )));
            }
        }
        if self.source_low[2] < 0.0 || self.source_high[2] > PI {
            return Err(DomainError::new("scene: tilts must lie in [0, π]"));
        }
        for i in 0..2 {
            let (lo, hi) = (self.start_low[i], self.start_high[i]);
            if !(lo <= hi && lo >= self.source_low[i] && hi <= self.source_high[i]) {
                return Err(DomainError::new(format!(
                    "scene: start region bound {i} must lie within the source bounds"
                )));
            }
        }
        Ok(())
    }
}
