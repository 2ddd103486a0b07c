//! SVG figures (plotters' SVG backend, no system fonts needed):
//!
//! - `metrics.svg`: the paper's layout — plan-found rate, success rate, TPR and TNR against the
//!   iteration, the mean over seeds with a ± one-standard-error band per strategy;
//! - `training.svg`: training statistics (`no_plan` answers, trajectory length, training-set
//!   size, training trajectories that reached their goal) in the same form;
//! - water plant only: `trajectory_types.svg` (the paper's Fig. 3: ratios of below-leaves
//!   successes, below-leaves spills and above-leaves spills among training trajectories) and
//!   `precondition_map_<j>.svg` (the paper's Fig. 4: `μ + 2σ` over the action plane for
//!   translation-only and rotation-only actions after iteration `j`, the precondition's
//!   boundary, the training actions, and the scene).

use super::Results;
use super::protocol::{IterationRecord, MapKind, PreconditionMap};
use super::report::{by_iteration, mean_se, metric};
use plotters::coord::Shift;
use plotters::prelude::*;
use precond_core::domain::WaterPlant;
use precond_core::domain::water_plant::{Rect, Scene};
use precond_core::planning::Strategy;
use std::path::Path;

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// `(iteration, mean, standard error)`.
type MeanPoint = (f64, f64, f64);

const FONT: &str = "sans-serif";

/// The colour of a strategy's lines.
pub fn strategy_color(s: Strategy) -> RGBColor {
    match s {
        Strategy::Active => RGBColor(31, 119, 180),
        Strategy::GoalConditioned => RGBColor(255, 127, 14),
        Strategy::Random => RGBColor(44, 160, 44),
    }
}

/// The test-time metrics plotted per strategy: (metric, panel label, is a rate).
const TEST_METRICS: [(&str, &str, bool); 4] = [
    ("plan_found_rate", "plan found", true),
    ("success_rate", "success", true),
    ("tpr", "TPR", true),
    ("tnr", "TNR", true),
];

/// Writes every figure of a run into `dir`.
pub fn write_all(dir: &Path, results: &Results) -> anyhow::Result<()> {
    let domain = results.config.domain.as_str();
    metric_figure(
        &dir.join("metrics.svg"),
        &format!("{domain}: test-time evaluation (mean ± s.e. over seeds)"),
        results,
        &TEST_METRICS,
    )?;
    metric_figure_over(
        &dir.join("metrics_by_transitions.svg"),
        &format!("{domain}: test-time evaluation against training transitions (mean over seeds)"),
        results,
        &TEST_METRICS,
        Axis::Transitions,
    )?;
    metric_figure(
        &dir.join("training.svg"),
        &format!("{domain}: training (mean ± s.e. over seeds)"),
        results,
        &[
            ("train_no_plan", "no_plan answers per batch", false),
            ("mean_traj_length", "trajectory length", false),
            ("n_train", "training transitions", false),
            ("train_goal_rate", "training goal reached", true),
        ],
    )?;
    if results.config.domain == super::DomainKind::WaterPlant {
        metric_figure(
            &dir.join("trajectory_types.svg"),
            &format!("{domain}: training trajectory types (ratio of the batch)"),
            results,
            &[
                ("below_success_ratio", "below leaves, success", true),
                ("below_spill_ratio", "below leaves, spill", true),
                ("above_spill_ratio", "above leaves, spill", true),
            ],
        )?;
        let plant = WaterPlant::default();
        let maps: Vec<&PreconditionMap> = results.runs.iter().flat_map(|r| &r.maps).collect();
        let mut iterations: Vec<usize> = maps.iter().map(|m| m.iteration).collect();
        iterations.dedup();
        for j in iterations {
            let pair: Vec<&PreconditionMap> =
                maps.iter().copied().filter(|m| m.iteration == j).collect();
            map_figure(
                &dir.join(format!("precondition_map_{j}.svg")),
                plant.scene(),
                &pair,
                j,
                results.config.map_tilt_degrees,
            )?;
        }
    }
    Ok(())
}

/// What the x axis of a metric figure counts.
#[derive(Clone, Copy, PartialEq)]
enum Axis {
    /// Learning iterations.
    Iterations,
    /// Training transitions executed so far (the mean over seeds at each iteration), so that
    /// strategies that execute more per iteration are compared at equal cost.
    Transitions,
}

/// One row of panels, one per metric: the mean over seeds per strategy with a ± s.e. band,
/// against iterations. Rates (`unit = true`) are drawn on `[0, 1]`.
fn metric_figure(
    path: &Path,
    title: &str,
    results: &Results,
    panels: &[(&str, &str, bool)],
) -> anyhow::Result<()> {
    metric_figure_over(path, title, results, panels, Axis::Iterations)
}

/// [`metric_figure`] against the given x axis.
fn metric_figure_over(
    path: &Path,
    title: &str,
    results: &Results,
    panels: &[(&str, &str, bool)],
    axis: Axis,
) -> anyhow::Result<()> {
    let cfg = &results.config;
    let root = SVGBackend::new(path, (420 * panels.len() as u32, 380)).into_drawing_area();
    root.fill(&WHITE)?;
    let root = root.titled(title, (FONT, 22))?;
    let areas = root.split_evenly((1, panels.len()));
    let x_of = |j: usize, g: &[&IterationRecord]| match axis {
        Axis::Iterations => Some(j as f64),
        Axis::Transitions => mean_se(g.iter().map(|r| Some(r.n_train as f64))).map(|(m, _, _)| m),
    };
    let mut x_max: f64 = 1.0;
    let mut all_series = Vec::new();
    for (name, _, _) in panels {
        let series: Vec<(Strategy, Vec<MeanPoint>)> = cfg
            .strategies
            .iter()
            .map(|&s| {
                let pts: Vec<MeanPoint> = by_iteration(results, s)
                    .iter()
                    .enumerate()
                    .filter_map(|(j, g)| {
                        let (m, se, _) = mean_se(g.iter().map(|r| metric(r, name)))?;
                        Some((x_of(j, g)?, m, se))
                    })
                    .collect();
                (s, pts)
            })
            .collect();
        for (_, pts) in &series {
            x_max = pts.iter().map(|p| p.0).fold(x_max, f64::max);
        }
        all_series.push(series);
    }
    for ((area, (_, label, unit)), series) in areas.iter().zip(panels).zip(all_series) {
        let (lo, hi) = if *unit {
            (0.0, 1.02)
        } else {
            let hi = series
                .iter()
                .flat_map(|(_, p)| p.iter().map(|(_, m, se)| m + se))
                .fold(0.0f64, f64::max);
            (0.0, if hi > 0.0 { hi * 1.08 } else { 1.0 })
        };
        let mut chart = ChartBuilder::on(area)
            .caption(*label, (FONT, 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(48)
            .build_cartesian_2d(0.0..x_max, lo..hi)?;
        chart
            .configure_mesh()
            .x_desc(match axis {
                Axis::Iterations => "iteration",
                Axis::Transitions => "training transitions",
            })
            .x_labels(cfg.iterations.clamp(2, 11))
            .x_label_formatter(&|x| format!("{x:.0}"))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for (s, pts) in &series {
            if pts.is_empty() {
                continue;
            }
            let color = strategy_color(*s);
            let mut band: Vec<(f64, f64)> = pts
                .iter()
                .map(|(x, m, se)| (*x, (m + se).min(hi)))
                .collect();
            band.extend(pts.iter().rev().map(|(x, m, se)| (*x, (m - se).max(lo))));
            chart.draw_series(std::iter::once(Polygon::new(
                band,
                color.mix(0.18).filled(),
            )))?;
            chart
                .draw_series(LineSeries::new(
                    pts.iter().map(|(x, m, _)| (*x, *m)),
                    color.stroke_width(2),
                ))?
                .label(s.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .label_font((FONT, 13))
            .draw()?;
    }
    root.present()?;
    Ok(())
}

/// The colour of a map cell: blues inside the precondition (darker further from the boundary),
/// reds outside; quantised so that runs of equal cells merge into one rectangle.
fn cell_color(upper: f64, d_max: f64) -> RGBColor {
    const BLUES: [RGBColor; 4] = [
        RGBColor(189, 215, 238),
        RGBColor(132, 180, 222),
        RGBColor(74, 140, 199),
        RGBColor(33, 94, 163),
    ];
    const REDS: [RGBColor; 5] = [
        RGBColor(253, 219, 199),
        RGBColor(244, 165, 130),
        RGBColor(214, 96, 77),
        RGBColor(178, 24, 43),
        RGBColor(103, 0, 31),
    ];
    if upper < d_max {
        BLUES[(((d_max - upper) / 0.1) as usize).min(BLUES.len() - 1)]
    } else {
        REDS[(((upper - d_max) / 0.2) as usize).min(REDS.len() - 1)]
    }
}

/// The translation-only and rotation-only maps of one iteration side by side.
fn map_figure(
    path: &Path,
    scene: &Scene,
    maps: &[&PreconditionMap],
    iteration: usize,
    tilt_degrees: f64,
) -> anyhow::Result<()> {
    let root = SVGBackend::new(path, (1100, 560)).into_drawing_area();
    root.fill(&WHITE)?;
    let root = root.titled(
        &format!(
            "water_plant, active, seed 0, after iteration {iteration}: μ + 2σ (blue: inside, \
             μ + 2σ < d_max = 0.1; red: outside); dots: training actions (white: deviation < d_max)"
        ),
        (FONT, 15),
    )?;
    let areas = root.split_evenly((1, 2));
    for (area, kind) in areas.iter().zip([MapKind::Translation, MapKind::Rotation]) {
        if let Some(map) = maps.iter().find(|m| m.kind == kind) {
            let caption = match kind {
                MapKind::Translation => "translation only (upright) to (x, y)".to_string(),
                MapKind::Rotation => format!("rotation only: tilt to {tilt_degrees}° at (x, y)"),
            };
            map_panel(area, scene, map, &caption)?;
        }
    }
    root.present()?;
    Ok(())
}

fn map_panel(
    area: &Area,
    scene: &Scene,
    map: &PreconditionMap,
    caption: &str,
) -> anyhow::Result<()> {
    let d_max = 0.1;
    let (x_lo, x_hi) = (scene.source_low[0], scene.source_high[0]);
    let y_hi = scene.source_high[1];
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FONT, 16))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(44)
        .build_cartesian_2d(x_lo..x_hi, 0.0..y_hi)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("source x (m)")
        .y_desc("source y (m)")
        .draw()?;
    let (nx, ny) = (map.xs.len(), map.ys.len());
    if nx >= 2 && ny >= 2 {
        let dx = (map.xs[1] - map.xs[0]) / 2.0;
        let dy = (map.ys[1] - map.ys[0]) / 2.0;
        let mut rects = Vec::new();
        for (r, row) in map.upper.iter().enumerate() {
            let (y0, y1) = (map.ys[r] - dy, map.ys[r] + dy);
            let mut c = 0;
            while c < row.len() {
                let color = cell_color(row[c], d_max);
                let mut e = c + 1;
                while e < row.len() && cell_color(row[e], d_max) == color {
                    e += 1;
                }
                rects.push(Rectangle::new(
                    [(map.xs[c] - dx, y0), (map.xs[e - 1] + dx, y1)],
                    color.filled(),
                ));
                c = e;
            }
        }
        chart.draw_series(rects)?;
        // The precondition's boundary: edges between inside and outside cells.
        let inside = |r: usize, c: usize| map.upper[r][c] < d_max;
        let mut edges = Vec::new();
        for r in 0..ny {
            for c in 0..nx {
                if c + 1 < nx && inside(r, c) != inside(r, c + 1) {
                    let x = map.xs[c] + dx;
                    edges.push(PathElement::new(
                        vec![(x, map.ys[r] - dy), (x, map.ys[r] + dy)],
                        BLACK.stroke_width(2),
                    ));
                }
                if r + 1 < ny && inside(r, c) != inside(r + 1, c) {
                    let y = map.ys[r] + dy;
                    edges.push(PathElement::new(
                        vec![(map.xs[c] - dx, y), (map.xs[c] + dx, y)],
                        BLACK.stroke_width(2),
                    ));
                }
            }
        }
        chart.draw_series(edges)?;
    }
    draw_scene(&mut chart, scene)?;
    chart.draw_series(map.points.iter().map(|&(x, y, dev)| {
        let style = if dev < d_max {
            WHITE.filled()
        } else {
            BLACK.filled()
        };
        Circle::new((x, y), 3, style)
    }))?;
    chart.draw_series(
        map.points
            .iter()
            .map(|&(x, y, _)| Circle::new((x, y), 3, BLACK.stroke_width(1))),
    )?;
    Ok(())
}

type MapChart<'a, 'b> = ChartContext<
    'a,
    SVGBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

fn rect(r: Rect, style: ShapeStyle) -> Rectangle<(f64, f64)> {
    Rectangle::new([(r.low.x, r.low.y), (r.high.x, r.high.y)], style)
}

/// The target (walls), the pot, the stem and the nominal leaves.
fn draw_scene(chart: &mut MapChart, scene: &Scene) -> anyhow::Result<()> {
    let wall = RGBColor(60, 60, 60).filled();
    let t = scene.target;
    let w = scene.target_wall;
    let walls = [
        Rect {
            low: t.low,
            high: precond_core::domain::water_plant::Vec2::new(t.low.x + w, t.high.y),
        },
        Rect {
            low: precond_core::domain::water_plant::Vec2::new(t.high.x - w, t.low.y),
            high: t.high,
        },
        Rect {
            low: t.low,
            high: precond_core::domain::water_plant::Vec2::new(t.high.x, t.low.y + w),
        },
    ];
    chart.draw_series(walls.into_iter().map(|r| rect(r, wall)))?;
    chart.draw_series([
        rect(scene.pot, RGBColor(140, 90, 50).filled()),
        rect(scene.stem, RGBColor(40, 120, 40).filled()),
    ])?;
    chart.draw_series(scene.leaves.iter().map(|leaf| {
        PathElement::new(
            leaf.points.iter().map(|p| (p.x, p.y)).collect::<Vec<_>>(),
            RGBColor(20, 140, 20).stroke_width(4),
        )
    }))?;
    Ok(())
}
