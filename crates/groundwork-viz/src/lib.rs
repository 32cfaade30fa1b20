//! groundwork-viz: bird's-eye pictures of a segmented scan.
//!
//! [`render`] draws, in the ground-aligned frame seen from above (x forward = up, y left =
//! left): every point coloured by what it is — ground by height or by probability,
//! non-ground grey, or, against labels, true/false positives and negatives in four colours
//! (the GMM paper's Figure 2) — then the proposals as oriented boxes with their ids (boxes
//! flagged as walls or too large faint, under the others), a legend of the colours, a
//! metric scale bar and the sensor. [`Image::to_png`] encodes the picture. Pure: no files.

mod draw;

use groundwork_detect::Proposal;

pub use draw::Image;

/// How points are coloured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Colouring<'a> {
    /// Ground by height (blue low → yellow high over the ground's 2–98 % height range),
    /// non-ground grey.
    Height,
    /// Ground by probability (amber at the threshold → green at 1), non-ground grey.
    Probability,
    /// Against the truth (`Some(true)` ground, `Some(false)` non-ground, `None` ignored):
    /// true ground green, false ground (non-ground called ground) red, missed ground blue,
    /// true non-ground grey, ignored dark grey.
    Errors(&'a [Option<bool>]),
}

/// Colours of [`Colouring::Errors`], for a legend.
pub const TRUE_GROUND: [u8; 3] = [60, 200, 80];
/// Non-ground called ground.
pub const FALSE_GROUND: [u8; 3] = [235, 50, 50];
/// Ground called non-ground.
pub const MISSED_GROUND: [u8; 3] = [60, 120, 255];
/// Non-ground called non-ground.
pub const NON_GROUND: [u8; 3] = [150, 150, 150];
const IGNORED: [u8; 3] = [70, 70, 70];
const BACKGROUND: [u8; 3] = [12, 12, 16];
const BOX: [u8; 3] = [255, 255, 255];
/// Boxes flagged as walls or too large for an object: faint, so they do not hide the scene.
const FLAGGED_BOX: [u8; 3] = [70, 60, 35];
const LEGEND_BACK: [u8; 3] = [0, 0, 0];
const TEXT: [u8; 3] = [230, 230, 230];
const SENSOR: [u8; 3] = [255, 60, 200];

/// The window drawn: a square of ±`range` metres around the sensor at `resolution` metres
/// per pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Half the side, metres.
    pub range: f32,
    /// Metres per pixel.
    pub resolution: f32,
}

impl Default for View {
    /// ±40 m at 0.08 m per pixel: 1000 × 1000 pixels, cars a dozen pixels wide at 40 m.
    fn default() -> Self {
        Self {
            range: 40.0,
            resolution: 0.08,
        }
    }
}

/// Why a picture cannot be drawn.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// Not one value per point.
    #[error("{what}: {got} values for {points} points")]
    Length {
        /// Which input.
        what: &'static str,
        /// Values given.
        got: usize,
        /// Points.
        points: usize,
    },
    /// A view that gives no picture or an absurd one.
    #[error(
        "view of ±{range} m at {resolution} m/pixel: need a positive range and at most 8000 × 8000 pixels"
    )]
    View {
        /// Half side.
        range: f32,
        /// Metres per pixel.
        resolution: f32,
    },
    /// PNG encoding failed.
    #[error("PNG encoding: {0}")]
    Png(String),
}

/// What to draw: points in the ground-aligned frame with their ground probabilities (≥
/// `threshold` is ground), and proposals.
#[derive(Debug, Clone, Copy)]
pub struct Scene<'a> {
    /// Points, ground-aligned frame (x forward, y left, z up), metres.
    pub points: &'a [[f32; 3]],
    /// Ground probability per point.
    pub probabilities: &'a [f32],
    /// Probability at or above which a point is ground.
    pub threshold: f32,
    /// Proposals to outline (ground-aligned frame).
    pub proposals: &'a [Proposal],
}

/// Ground by height: blue low → yellow high.
const HEIGHT: [[u8; 3]; 4] = [
    [40, 60, 200],
    [30, 170, 190],
    [120, 210, 80],
    [250, 220, 60],
];
/// Ground by probability: amber at the threshold → green at 1.
const PROBABILITY: [[u8; 3]; 2] = [[230, 150, 40], [60, 210, 90]];

fn lerp(a: [u8; 3], b: [u8; 3], t: f32) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0);
    std::array::from_fn(|k| (f32::from(a[k]) + (f32::from(b[k]) - f32::from(a[k])) * t) as u8)
}

/// A colour ramp through several stops, t in [0, 1].
fn ramp(stops: &[[u8; 3]], t: f32) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0) * (stops.len() - 1) as f32;
    let k = (t.floor() as usize).min(stops.len() - 2);
    lerp(stops[k], stops[k + 1], t - k as f32)
}

fn quantile(mut v: Vec<f32>, q: f32) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let k = ((v.len() - 1) as f32 * q) as usize;
    *v.select_nth_unstable_by(k, f32::total_cmp).1
}

/// Draws a scene.
pub fn render(
    scene: &Scene<'_>,
    colouring: Colouring<'_>,
    view: View,
) -> Result<Image, RenderError> {
    let n = scene.points.len();
    if scene.probabilities.len() != n {
        return Err(RenderError::Length {
            what: "probabilities",
            got: scene.probabilities.len(),
            points: n,
        });
    }
    if let Colouring::Errors(t) = colouring
        && t.len() != n
    {
        return Err(RenderError::Length {
            what: "labels",
            got: t.len(),
            points: n,
        });
    }
    let side = 2.0 * view.range / view.resolution;
    if !(view.range > 0.0 && view.resolution > 0.0 && side.is_finite() && side <= 8000.0) {
        return Err(RenderError::View {
            range: view.range,
            resolution: view.resolution,
        });
    }
    let mut img = Image::new(side.ceil() as u32, side.ceil() as u32, BACKGROUND);
    let thr = scene.threshold;
    let is_ground = |i: usize| scene.probabilities[i] >= thr;
    let (lo, hi) = {
        let z: Vec<f32> = (0..n)
            .filter(|&i| is_ground(i))
            .map(|i| scene.points[i][2])
            .collect();
        (quantile(z.clone(), 0.02), quantile(z, 0.98))
    };
    let colour = |i: usize| -> [u8; 3] {
        let g = is_ground(i);
        match colouring {
            Colouring::Height if g => {
                ramp(&HEIGHT, (scene.points[i][2] - lo) / (hi - lo).max(0.05))
            }
            Colouring::Probability if g => ramp(
                &PROBABILITY,
                (scene.probabilities[i] - thr) / (1.0 - thr).max(1e-6),
            ),
            Colouring::Height | Colouring::Probability => NON_GROUND,
            Colouring::Errors(truth) => match (g, truth[i]) {
                (_, None) => IGNORED,
                (true, Some(true)) => TRUE_GROUND,
                (true, Some(false)) => FALSE_GROUND,
                (false, Some(true)) => MISSED_GROUND,
                (false, Some(false)) => NON_GROUND,
            },
        }
    };
    // Seen from above: the highest point of a pixel is the one on top.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_unstable_by(|&a, &b| scene.points[a][2].total_cmp(&scene.points[b][2]));
    let to_px = |x: f32, y: f32| -> (f32, f32) {
        (
            (view.range - y) / view.resolution,
            (view.range - x) / view.resolution,
        )
    };
    for i in order {
        let [x, y, _] = scene.points[i];
        let (c, r) = to_px(x, y);
        img.put(c as i64, r as i64, colour(i));
    }
    // Flagged boxes first, faint: the object-like ones are drawn over them.
    let mut boxes: Vec<&Proposal> = scene.proposals.iter().collect();
    boxes.sort_by_key(|p| p.flags.is_object_like());
    for p in boxes {
        let (s, c) = p.yaw.sin_cos();
        let (hl, hw) = (p.length / 2.0, p.width / 2.0);
        let corner =
            |u: f32, v: f32| to_px(p.center[0] + u * c - v * s, p.center[1] + u * s + v * c);
        let k = [
            corner(hl, hw),
            corner(-hl, hw),
            corner(-hl, -hw),
            corner(hl, -hw),
        ];
        let colour = if p.flags.is_object_like() {
            BOX
        } else {
            FLAGGED_BOX
        };
        for e in 0..4 {
            img.line(k[e], k[(e + 1) % 4], colour);
        }
        if p.flags.is_object_like() {
            let (cx, cy) = to_px(p.center[0], p.center[1]);
            img.text(&p.id.to_string(), cx as i64 + 4, cy as i64 - 8, 2, BOX);
        }
    }
    // The sensor: a triangle pointing forward (up).
    let (sx, sy) = to_px(0.0, 0.0);
    let a = 0.8 / view.resolution;
    img.line((sx, sy - 1.5 * a), (sx - a, sy + a), SENSOR);
    img.line((sx - a, sy + a), (sx + a, sy + a), SENSOR);
    img.line((sx + a, sy + a), (sx, sy - 1.5 * a), SENSOR);
    // Scale bar: a round length near a fifth of the picture, bottom left.
    let want = view.range * 0.4;
    let metres = [1.0f32, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0]
        .into_iter()
        .rev()
        .find(|&m| m <= want)
        .unwrap_or(1.0);
    let (h, len) = (img.height() as f32, metres / view.resolution);
    let (x0, y0) = (20.0, h - 24.0);
    for dy in 0..3 {
        img.line((x0, y0 + dy as f32), (x0 + len, y0 + dy as f32), BOX);
    }
    img.line((x0, y0 - 6.0), (x0, y0 + 8.0), BOX);
    img.line((x0 + len, y0 - 6.0), (x0 + len, y0 + 8.0), BOX);
    img.text(&format!("{metres} m"), x0 as i64, y0 as i64 - 22, 2, BOX);
    let flagged = scene.proposals.iter().any(|p| !p.flags.is_object_like());
    legend(
        &mut img,
        colouring,
        (lo, hi, thr),
        !scene.proposals.is_empty(),
        flagged,
    );
    Ok(img)
}

/// The legend, top left: what each colour means (and the numbers a ramp spans).
fn legend(
    img: &mut Image,
    colouring: Colouring<'_>,
    (lo, hi, thr): (f32, f32, f32),
    boxes: bool,
    flagged: bool,
) {
    enum Entry {
        Swatch([u8; 3], String),
        Ramp(&'static [[u8; 3]], String),
    }
    const HEIGHT_RAMP: [[u8; 3]; 4] = HEIGHT;
    let mut entries = match colouring {
        Colouring::Errors(_) => vec![
            Entry::Swatch(TRUE_GROUND, "ground, called ground".into()),
            Entry::Swatch(FALSE_GROUND, "non-ground called ground".into()),
            Entry::Swatch(MISSED_GROUND, "ground missed".into()),
            Entry::Swatch(NON_GROUND, "non-ground".into()),
            Entry::Swatch(IGNORED, "ignored (unlabeled)".into()),
        ],
        Colouring::Height => vec![
            Entry::Ramp(&HEIGHT_RAMP, format!("ground height {lo:.2} to {hi:.2} m")),
            Entry::Swatch(NON_GROUND, "non-ground".into()),
        ],
        Colouring::Probability => vec![
            Entry::Ramp(&PROBABILITY, format!("ground probability {thr:.2} to 1")),
            Entry::Swatch(NON_GROUND, "non-ground".into()),
        ],
    };
    if boxes {
        entries.push(Entry::Swatch(BOX, "proposal (id)".into()));
    }
    if flagged {
        entries.push(Entry::Swatch(FLAGGED_BOX, "wall or too large".into()));
    }
    // Scale 2 on pictures of 600 pixels and more, 1 below.
    let s = if img.width() >= 600 { 2 } else { 1 };
    let (line, pad, swatch) = (12 * s, 6 * s, 24 * s);
    let longest = entries
        .iter()
        .map(|e| match e {
            Entry::Swatch(_, t) | Entry::Ramp(_, t) => t.len() as i64,
        })
        .max()
        .unwrap_or(0);
    let width = pad * 3 + swatch + longest * 8 * s;
    img.fill(
        0,
        0,
        width,
        pad * 2 + line * entries.len() as i64,
        LEGEND_BACK,
    );
    for (k, e) in entries.iter().enumerate() {
        let y = pad + line * k as i64;
        let text = match e {
            Entry::Swatch(c, t) => {
                img.fill(pad, y + s, swatch, 8 * s, *c);
                t
            }
            Entry::Ramp(stops, t) => {
                for dx in 0..swatch {
                    let c = ramp(stops, dx as f32 / (swatch - 1) as f32);
                    img.fill(pad + dx, y + s, 1, 8 * s, c);
                }
                t
            }
        };
        img.text(text, pad * 2 + swatch, y + s, s, TEXT);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene_points() -> (Vec<[f32; 3]>, Vec<f32>) {
        let mut pts = Vec::new();
        let mut probs = Vec::new();
        for i in -50..50 {
            for j in -50..50 {
                pts.push([i as f32 * 0.4, j as f32 * 0.4, 0.0]);
                probs.push(1.0);
            }
        }
        // An object ahead, 10 m forward.
        for k in 0..50 {
            pts.push([10.0, -1.0 + 0.04 * k as f32, 1.0]);
            probs.push(0.0);
        }
        (pts, probs)
    }

    #[test]
    fn points_land_where_they_are_seen_from_above() {
        let (pts, probs) = scene_points();
        let scene = Scene {
            points: &pts,
            probabilities: &probs,
            threshold: 0.5,
            proposals: &[],
        };
        let view = View {
            range: 20.0,
            resolution: 0.1,
        };
        let img = render(&scene, Colouring::Probability, view).unwrap();
        assert_eq!((img.width(), img.height()), (400, 400));
        // The object 10 m forward is grey, 100 pixels above the centre.
        assert_eq!(img.get(200, 100), NON_GROUND);
        // Ground at full probability is green.
        assert_eq!(img.get(260, 300), [60, 210, 90]);
        // Errors: the object called ground would be red.
        let truth: Vec<Option<bool>> = probs.iter().map(|&p| Some(p < 0.5)).collect();
        let img = render(&scene, Colouring::Errors(&truth), view).unwrap();
        assert_eq!(img.get(200, 100), MISSED_GROUND);
        assert_eq!(img.get(260, 300), FALSE_GROUND);
        let png = img.to_png().unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn the_legend_names_every_colour_drawn() {
        let (pts, probs) = scene_points();
        let scene = Scene {
            points: &pts,
            probabilities: &probs,
            threshold: 0.5,
            proposals: &[],
        };
        let view = View {
            range: 20.0,
            resolution: 0.1,
        };
        let truth: Vec<Option<bool>> = probs.iter().map(|&p| Some(p >= 0.5)).collect();
        let img = render(&scene, Colouring::Errors(&truth), view).unwrap();
        // One swatch per line, top left (400 pixels: font scale 1, lines of 12 pixels).
        let swatch = |k: u32| img.get(10, 6 + 12 * k + 4);
        assert_eq!(
            [swatch(0), swatch(1), swatch(2), swatch(3), swatch(4)],
            [
                TRUE_GROUND,
                FALSE_GROUND,
                MISSED_GROUND,
                NON_GROUND,
                IGNORED
            ]
        );
        // Text beside each: light pixels right of the swatch.
        let lit = (36..120).any(|c| (7..15).any(|r| img.get(c, r) == TEXT));
        assert!(lit);
        // Height: a ramp from blue to yellow.
        let img = render(&scene, Colouring::Height, view).unwrap();
        assert_eq!(img.get(6, 10), HEIGHT[0]);
        assert_eq!(img.get(29, 10), HEIGHT[3]);
    }

    #[test]
    fn bad_lengths_and_views_are_errors() {
        let (pts, probs) = scene_points();
        let scene = Scene {
            points: &pts,
            probabilities: &probs[1..],
            threshold: 0.5,
            proposals: &[],
        };
        assert!(render(&scene, Colouring::Height, View::default()).is_err());
        let scene = Scene {
            probabilities: &probs,
            ..scene
        };
        let tiny = View {
            range: 100.0,
            resolution: 0.001,
        };
        assert!(matches!(
            render(&scene, Colouring::Height, tiny),
            Err(RenderError::View { .. })
        ));
    }
}
