//! Line and scatter plots as SVG text (plotters' SVG backend: text is left to the viewer's
//! fonts, so nothing here needs a font file).

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::ReportError;

/// Plot size, pixels.
pub const SIZE: (u32, u32) = (680, 340);

/// One line (or set of markers) of a figure.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text.
    pub label: String,
    /// `(x, y)`; non-finite points are left out.
    pub points: Vec<(f64, f64)>,
    /// Drawn dashed (a reference such as the ground truth).
    pub dashed: bool,
    /// Markers only, no line.
    pub markers: bool,
    /// Colour index (series with the same index share a colour).
    pub colour: usize,
    /// Text drawn beside each point (markers), empty for none.
    pub point_labels: Vec<String>,
}

impl Series {
    /// A solid line.
    pub fn line(label: impl Into<String>, points: Vec<(f64, f64)>, colour: usize) -> Self {
        Self {
            label: label.into(),
            points,
            dashed: false,
            markers: false,
            colour,
            point_labels: Vec::new(),
        }
    }

    /// Markers, each with a text beside it.
    pub fn markers(
        label: impl Into<String>,
        points: Vec<(f64, f64)>,
        point_labels: Vec<String>,
        colour: usize,
    ) -> Self {
        Self {
            label: label.into(),
            points,
            dashed: false,
            markers: true,
            colour,
            point_labels,
        }
    }

    /// A dashed horizontal reference line at `y` over `[x0, x1]`.
    pub fn reference(label: impl Into<String>, y: f64, x0: f64, x1: f64, colour: usize) -> Self {
        Self {
            label: label.into(),
            points: vec![(x0, y), (x1, y)],
            dashed: true,
            markers: false,
            colour,
            point_labels: Vec::new(),
        }
    }
}

/// A figure: axes, labels and series.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// Caption.
    pub title: String,
    /// Axis labels (with units).
    pub x_label: String,
    pub y_label: String,
    /// What to draw.
    pub series: Vec<Series>,
    /// Logarithmic y axis (used only when every y is positive).
    pub log_y: bool,
    /// Logarithmic x axis (used only when every x is positive).
    pub log_x: bool,
}

/// Colours for up to 10 series (Tableau 10), then they repeat.
const COLOURS: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

fn colour(i: usize) -> RGBColor {
    COLOURS[i % COLOURS.len()]
}

/// `[lo, hi]` of `values` padded by 5 % (a single value widened to a visible range).
fn span(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() || !hi.is_finite() {
        return None;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else if lo != 0.0 {
        0.05 * lo.abs()
    } else {
        0.5
    };
    Some((lo - pad, hi + pad))
}

fn plot_error(title: &str, e: impl std::fmt::Display) -> ReportError {
    ReportError::Plot {
        title: title.to_string(),
        message: e.to_string(),
    }
}

impl Figure {
    /// The finite points of every series.
    fn finite(&self) -> Vec<Series> {
        self.series
            .iter()
            .map(|s| {
                let keep = |(x, y): &(f64, f64)| {
                    x.is_finite()
                        && y.is_finite()
                        && (!self.log_y || *y > 0.0)
                        && (!self.log_x || *x > 0.0)
                };
                Series {
                    points: s.points.iter().copied().filter(keep).collect(),
                    point_labels: s
                        .points
                        .iter()
                        .zip(&s.point_labels)
                        .filter(|(p, _)| keep(p))
                        .map(|(_, l)| l.clone())
                        .collect(),
                    ..s.clone()
                }
            })
            .filter(|s| !s.points.is_empty())
            .collect()
    }

    /// The SVG document, or `None` when no series has a finite point. A logarithmic axis is
    /// drawn as log10 of the values on a linear axis, its ticks labelled with the values.
    pub fn svg(&self) -> Result<Option<String>, ReportError> {
        let mut series = self.finite();
        let all_y = |s: &[Series]| {
            s.iter()
                .flat_map(|s| s.points.iter().map(|p| p.1))
                .collect::<Vec<_>>()
        };
        let all_x = |s: &[Series]| {
            s.iter()
                .flat_map(|s| s.points.iter().map(|p| p.0))
                .collect::<Vec<_>>()
        };
        let log_y = self.log_y && all_y(&series).iter().all(|y| *y > 0.0);
        let log_x = self.log_x && all_x(&series).iter().all(|x| *x > 0.0);
        let integer_x = !log_x && all_x(&series).iter().all(|x| x.fract() == 0.0);
        for s in &mut series {
            for p in &mut s.points {
                if log_x {
                    p.0 = p.0.log10();
                }
                if log_y {
                    p.1 = p.1.log10();
                }
            }
        }
        let (Some(xs), Some(ys)) = (
            span(all_x(&series).into_iter()),
            span(all_y(&series).into_iter()),
        ) else {
            return Ok(None);
        };
        let mut buf = String::new();
        {
            let root = SVGBackend::with_string(&mut buf, SIZE).into_drawing_area();
            root.fill(&WHITE).map_err(|e| plot_error(&self.title, e))?;
            let (plot, legend) = root.split_horizontally(SIZE.0 - LEGEND_WIDTH);
            self.draw(&plot, &series, xs, ys, (log_x, log_y, integer_x))
                .map_err(|e| plot_error(&self.title, e))?;
            draw_legend(&legend, &series).map_err(|e| plot_error(&self.title, e))?;
            root.present().map_err(|e| plot_error(&self.title, e))?;
        }
        Ok(Some(buf))
    }

    fn draw(
        &self,
        area: &DrawingArea<SVGBackend<'_>, Shift>,
        series: &[Series],
        x: (f64, f64),
        y: (f64, f64),
        (log_x, log_y, integer_x): (bool, bool, bool),
    ) -> Result<(), Box<dyn std::error::Error + '_>> {
        let mut chart = ChartBuilder::on(area)
            .caption(&self.title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(x.0..x.1, y.0..y.1)?;
        let tick = |v: &f64, log: bool| {
            if log {
                crate::text::num(10f64.powf(*v))
            } else {
                crate::text::num(*v)
            }
        };
        let x_fmt = |v: &f64| {
            if integer_x {
                if (v - v.round()).abs() < 1e-9 {
                    format!("{}", v.round() as i64)
                } else {
                    String::new()
                }
            } else {
                tick(v, log_x)
            }
        };
        let y_fmt = |v: &f64| tick(v, log_y);
        let x_labels = if integer_x {
            ((x.1 - x.0).round() as usize + 1).clamp(2, 10)
        } else {
            8
        };
        let y_label = if log_y {
            format!("{} (log scale)", self.y_label)
        } else {
            self.y_label.clone()
        };
        chart
            .configure_mesh()
            .x_desc(&self.x_label)
            .y_desc(&y_label)
            .x_labels(x_labels)
            .y_labels(7)
            .x_label_formatter(&x_fmt)
            .y_label_formatter(&y_fmt)
            .label_style(("sans-serif", 12))
            .axis_desc_style(("sans-serif", 13))
            .bold_line_style(RGBColor(225, 225, 225))
            .light_line_style(TRANSPARENT)
            .draw()?;
        for s in series {
            let c = colour(s.colour);
            let pts = s.points.clone();
            if s.markers {
                chart.draw_series(pts.iter().map(|p| Circle::new(*p, 4, c.filled())))?;
                chart.draw_series(pts.iter().zip(&s.point_labels).map(|(p, l)| {
                    EmptyElement::at(*p)
                        + plotters::element::Text::new(l.clone(), (6, -14), ("sans-serif", 11))
                }))?;
            } else if s.dashed {
                chart.draw_series(DashedLineSeries::new(pts, 6, 4, c.stroke_width(2)))?;
            } else {
                let single = pts.len() == 1;
                chart.draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))?;
                if single {
                    chart.draw_series(pts.iter().map(|p| Circle::new(*p, 3, c.filled())))?;
                }
            }
        }
        Ok(())
    }
}

/// Width of the legend beside the plot, pixels.
const LEGEND_WIDTH: u32 = 180;

/// The legend, beside the plot (never over the data): a sample of each series' line, dash
/// or marker, and its label.
fn draw_legend(
    area: &DrawingArea<SVGBackend<'_>, Shift>,
    series: &[Series],
) -> Result<(), Box<dyn std::error::Error>> {
    let font = ("sans-serif", 12).into_font().color(&BLACK);
    for (i, s) in series.iter().enumerate() {
        let y = 40 + 20 * i as i32;
        let c = colour(s.colour);
        if s.markers {
            area.draw(&Circle::new((14, y), 4, c.filled()))?;
        } else if s.dashed {
            for x0 in [4, 14] {
                area.draw(&PathElement::new(
                    vec![(x0, y), (x0 + 6, y)],
                    c.stroke_width(2),
                ))?;
            }
        } else {
            area.draw(&PathElement::new(vec![(4, y), (24, y)], c.stroke_width(2)))?;
        }
        area.draw(&plotters::element::Text::new(
            s.label.clone(),
            (30, y - 7),
            font.clone(),
        ))?;
    }
    Ok(())
}

/// `svg` without its `xmlns` attribute, for inlining in HTML (the HTML parser puts `<svg>` in
/// the SVG namespace by itself).
pub fn inline(svg: &str) -> String {
    svg.replacen(r#" xmlns="http://www.w3.org/2000/svg""#, "", 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_figure_draws_its_series_and_labels() {
        let f = Figure {
            title: "loss <warmup>".into(),
            x_label: "epoch".into(),
            y_label: "loss".into(),
            series: vec![
                Series::line("a & b", vec![(0.0, 1.0), (1.0, 0.5), (2.0, f64::NAN)], 0),
                Series::reference("truth", 0.7, 0.0, 2.0, 1),
            ],
            log_y: true,
            log_x: false,
        };
        let svg = f.svg().unwrap().unwrap();
        assert!(svg.starts_with("<svg"), "{svg}");
        assert!(svg.contains("loss &lt;warmup&gt;"), "title escaped");
        assert!(svg.contains("a &amp; b") && svg.contains("truth"));
        assert!(!inline(&svg).contains("http"));
    }

    #[test]
    fn a_figure_without_finite_points_is_none() {
        let f = Figure {
            title: "empty".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            series: vec![Series::line("nan", vec![(0.0, f64::NAN)], 0)],
            log_y: false,
            log_x: false,
        };
        assert!(f.svg().unwrap().is_none());
    }
}
