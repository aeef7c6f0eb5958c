//! A box-and-whisker plot written as SVG by hand (no plotting crate), as
//! the paper draws its round trips: one group per payload size (or
//! scenario), one box per broker in a group. The box spans the quartiles,
//! the thick line is the median, the whiskers reach the minimum and the
//! maximum, a diamond marks the mean and a cross the 99th percentile. The
//! latency axis is logarithmic (a few slow outliers would otherwise
//! flatten every box), with 1-2-5 gridlines.

use crate::histogram::BoxStats;
use crate::report::micros;
use std::fmt::Write;

/// One group of boxes on the x axis.
#[derive(Debug, Clone)]
pub struct Group {
    /// Label under the group.
    pub label: String,
    /// (series name, statistics), in series order.
    pub boxes: Vec<(String, BoxStats)>,
}

const COLORS: [&str; 4] = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728"];
const BOX_WIDTH: f64 = 30.0;
const BOX_GAP: f64 = 14.0;
const GROUP_GAP: f64 = 40.0;
const LEFT: f64 = 80.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 50.0;
const PLOT_HEIGHT: f64 = 320.0;
const BOTTOM: f64 = 120.0;
const MIN_PLOT_WIDTH: f64 = 560.0;

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The plot; `series` names the colours in the legend (empty: one
/// unnamed series).
pub fn box_plot(title: &str, groups: &[Group], series: &[String]) -> String {
    let per_group = groups
        .iter()
        .map(|g| g.boxes.len())
        .max()
        .unwrap_or(1)
        .max(1);
    let min_group_width = per_group as f64 * (BOX_WIDTH + BOX_GAP) - BOX_GAP + GROUP_GAP;
    let plot_width = (groups.len().max(1) as f64 * min_group_width).max(MIN_PLOT_WIDTH);
    // Groups share the plot's width evenly.
    let group_width = plot_width / groups.len().max(1) as f64;
    let width = LEFT + plot_width + RIGHT;
    let height = TOP + PLOT_HEIGHT + BOTTOM;

    // Logarithmic axis over whole decades covering every value.
    let values = groups
        .iter()
        .flat_map(|g| g.boxes.iter())
        .flat_map(|(_, b)| [b.min_us, b.max_us, b.p99_us, b.mean_us]);
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let (lo, hi) = if lo > hi { (1.0, 10.0) } else { (lo, hi) };
    let lo_dec = lo.log10().floor();
    let mut hi_dec = hi.log10().ceil();
    if hi_dec <= lo_dec {
        hi_dec = lo_dec + 1.0;
    }
    let y = |v: f64| -> f64 {
        let v = v.max(10f64.powf(lo_dec));
        TOP + PLOT_HEIGHT * (1.0 - (v.log10() - lo_dec) / (hi_dec - lo_dec))
    };

    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0}" height="{height:.0}" viewBox="0 0 {width:.0} {height:.0}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(
        s,
        r#"<rect x="0" y="0" width="{width:.0}" height="{height:.0}" fill="white"/>"#
    );
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="28" text-anchor="middle" font-size="15" font-weight="bold">{}</text>"#,
        width / 2.0,
        escape(title)
    );
    // Gridlines and labels at 1, 2, 5 × 10^k.
    let mut decade = lo_dec as i32;
    while f64::from(decade) <= hi_dec {
        for m in [1.0, 2.0, 5.0] {
            let v = m * 10f64.powi(decade);
            if v.log10() < lo_dec - 1e-9 || v.log10() > hi_dec + 1e-9 {
                continue;
            }
            let yy = y(v);
            let (stroke, dash) = if m == 1.0 {
                ("#bbbbbb", "")
            } else {
                ("#e3e3e3", r#" stroke-dasharray="3,3""#)
            };
            let _ = writeln!(
                s,
                r#"<line x1="{LEFT}" y1="{yy:.1}" x2="{:.1}" y2="{yy:.1}" stroke="{stroke}"{dash}/>"#,
                LEFT + plot_width
            );
            let _ = writeln!(
                s,
                r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"#,
                LEFT - 6.0,
                yy + 4.0,
                escape(&micros(v))
            );
        }
        decade += 1;
    }
    let _ = writeln!(
        s,
        r#"<text x="18" y="{:.1}" text-anchor="middle" transform="rotate(-90 18 {:.1})">round-trip time (log scale)</text>"#,
        TOP + PLOT_HEIGHT / 2.0,
        TOP + PLOT_HEIGHT / 2.0
    );
    let _ = writeln!(
        s,
        r##"<rect x="{LEFT}" y="{TOP}" width="{plot_width:.1}" height="{PLOT_HEIGHT}" fill="none" stroke="#444"/>"##
    );

    for (g, group) in groups.iter().enumerate() {
        let used = group.boxes.len() as f64 * (BOX_WIDTH + BOX_GAP) - BOX_GAP;
        let group_x = LEFT + g as f64 * group_width + (group_width - used) / 2.0;
        for (i, (_, b)) in group.boxes.iter().enumerate() {
            let color = COLORS[i % COLORS.len()];
            let x0 = group_x + i as f64 * (BOX_WIDTH + BOX_GAP);
            let xc = x0 + BOX_WIDTH / 2.0;
            let (ymin, yq1, ymed, yq3, ymax) = (
                y(b.min_us),
                y(b.q1_us),
                y(b.median_us),
                y(b.q3_us),
                y(b.max_us),
            );
            // Whiskers and caps.
            for (from, to) in [(ymin, yq1), (yq3, ymax)] {
                let _ = writeln!(
                    s,
                    r#"<line x1="{xc:.1}" y1="{from:.1}" x2="{xc:.1}" y2="{to:.1}" stroke="{color}"/>"#
                );
            }
            for cap in [ymin, ymax] {
                let _ = writeln!(
                    s,
                    r#"<line x1="{:.1}" y1="{cap:.1}" x2="{:.1}" y2="{cap:.1}" stroke="{color}"/>"#,
                    xc - BOX_WIDTH / 4.0,
                    xc + BOX_WIDTH / 4.0
                );
            }
            let _ = writeln!(
                s,
                r#"<rect x="{x0:.1}" y="{yq3:.1}" width="{BOX_WIDTH}" height="{:.1}" fill="{color}" fill-opacity="0.3" stroke="{color}"/>"#,
                (yq1 - yq3).max(0.5)
            );
            let _ = writeln!(
                s,
                r#"<line x1="{x0:.1}" y1="{ymed:.1}" x2="{:.1}" y2="{ymed:.1}" stroke="{color}" stroke-width="3"/>"#,
                x0 + BOX_WIDTH
            );
            let ym = y(b.mean_us);
            let _ = writeln!(
                s,
                r#"<polygon points="{xc:.1},{:.1} {:.1},{ym:.1} {xc:.1},{:.1} {:.1},{ym:.1}" fill="white" stroke="black"/>"#,
                ym - 4.0,
                xc + 4.0,
                ym + 4.0,
                xc - 4.0
            );
            let yp = y(b.p99_us);
            let _ = writeln!(
                s,
                r#"<path d="M{:.1},{:.1} L{:.1},{:.1} M{:.1},{:.1} L{:.1},{:.1}" stroke="black"/>"#,
                xc - 3.5,
                yp - 3.5,
                xc + 3.5,
                yp + 3.5,
                xc - 3.5,
                yp + 3.5,
                xc + 3.5,
                yp - 3.5
            );
            let _ = writeln!(
                s,
                r#"<text x="{xc:.1}" y="{:.1}" text-anchor="middle" font-size="10">{}</text>"#,
                TOP + PLOT_HEIGHT + 14.0,
                escape(&micros(b.median_us))
            );
        }
        let _ = writeln!(
            s,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
            group_x + used / 2.0,
            TOP + PLOT_HEIGHT + 32.0,
            escape(&group.label)
        );
    }

    // Legend.
    let mut lx = LEFT;
    let ly = TOP + PLOT_HEIGHT + 62.0;
    for (i, name) in series.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let _ = writeln!(
            s,
            r#"<rect x="{lx:.1}" y="{:.1}" width="14" height="14" fill="{color}" fill-opacity="0.3" stroke="{color}"/>"#,
            ly - 11.0
        );
        let _ = writeln!(
            s,
            r#"<text x="{:.1}" y="{ly:.1}">{}</text>"#,
            lx + 20.0,
            escape(name)
        );
        lx += 30.0 + 8.0 * name.chars().count() as f64;
    }
    let _ = writeln!(
        s,
        r##"<text x="{LEFT}" y="{:.1}" font-size="11" fill="#444">box: first to third quartile; thick line: median (its value under the axis)</text>"##,
        ly + 22.0
    );
    let _ = writeln!(
        s,
        r##"<text x="{LEFT}" y="{:.1}" font-size="11" fill="#444">whiskers: minimum and maximum; ◇ mean; × 99th percentile</text>"##,
        ly + 38.0
    );
    s.push_str("</svg>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_a_box_per_series() {
        let stats = BoxStats {
            count: 10,
            mean_us: 150.0,
            min_us: 90.0,
            q1_us: 110.0,
            median_us: 140.0,
            q3_us: 170.0,
            p99_us: 400.0,
            max_us: 900.0,
        };
        let groups = vec![Group {
            label: "16 B <one in flight>".into(),
            boxes: vec![("a".into(), stats), ("b".into(), stats)],
        }];
        let svg = box_plot("t & t", &groups, &["a".into(), "b".into()]);
        assert!(svg.starts_with("<svg"));
        assert!(svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("fill-opacity=\"0.3\"").count(), 4);
        assert!(svg.contains("t &amp; t"));
        assert!(svg.contains("&lt;one in flight&gt;"));
    }
}
