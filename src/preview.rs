//! PNG previews of images for people: viridis colours, north up and east left as DS9 shows a
//! FITS image, a colour bar with tick labels and a title. Text comes from a built-in 5 x 7
//! bitmap font so that no font-rendering dependency is needed.

use crate::fits::TempSibling;
use crate::{Error, Result};
use std::io::Write;
use std::path::Path;

/// How pixel values map to colours.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PreviewScale {
    /// From the image minimum (bottom colour) to its maximum (top colour).
    Linear,
    /// `log10(x / peak)` over `[-log10(dynamic_range), 0]`: pixels below `peak / dynamic_range`
    /// (negative ones included) take the bottom colour, as radio images are usually shown.
    Log { dynamic_range: f64 },
    /// Signed, for images with negative pixels that mean something (dirty, residual, PSF,
    /// restored): `asinh(x / softening)` symmetric about zero, linear within a few
    /// `softening` (set it to the noise) and logarithmic beyond, on a diverging palette
    /// whose white is zero, so negative sidelobes and noise read as such.
    Signed { softening: f64 },
}

/// Writes a preview of `image` (`size_x * size_y`, row-major, row 0 at the bottom as in FITS)
/// to `path`, through a temporary sibling renamed into place so no partial file is left.
///
/// Small images are enlarged by an integer factor (nearest neighbour) to about 512 pixels;
/// images over 1024 pixels are reduced by an integer factor, each displayed pixel taking the
/// value of largest magnitude in its block (the maximum for the log scale) so that point
/// sources stay visible. Non-finite pixels are shown grey.
#[cfg(test)]
pub fn write_png(path: &Path, image: &[f64], size_x: usize, size_y: usize, scale: PreviewScale, title: &str) -> Result<()> {
    write_png_on_sky(path, image, size_x, size_y, scale, title, None)
}

/// Where an image lies on the sky, for its preview: the pixel size, and the restoring beam
/// (drawn as an ellipse in the lower left corner, as viewers do) where there is one. A scale
/// bar of a round angle goes in the lower right.
#[derive(Clone, Copy, Debug)]
pub struct SkyFrame {
    pub pixel_arcsec: f64,
    /// FWHM major and minor axes (arcsec) and position angle (degrees east of north).
    pub beam: Option<(f64, f64, f64)>,
}

/// [`write_png`] with the beam and a scale bar drawn over the image (`sky`).
pub fn write_png_on_sky(path: &Path, image: &[f64], size_x: usize, size_y: usize, scale: PreviewScale, title: &str, sky: Option<&SkyFrame>) -> Result<()> {
    let canvas = render(image, size_x, size_y, scale, title, sky)?;
    let tmp = TempSibling::new(path)?;
    let file = std::fs::File::create(tmp.path()).map_err(|e| Error::io(path, e))?;
    let mut out = std::io::BufWriter::new(file);
    let encoding_error = |e: png::EncodingError| match e {
        png::EncodingError::IoError(io) => Error::io(path, io),
        other => Error::io(path, std::io::Error::other(format!("PNG encoding failed: {other}"))),
    };
    let mut encoder = png::Encoder::new(&mut out, canvas.width as u32, canvas.height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(encoding_error)?;
    writer.write_image_data(&canvas.rgb).map_err(encoding_error)?;
    writer.finish().map_err(encoding_error)?;
    out.flush().map_err(|e| Error::io(path, e))?;
    drop(out);
    tmp.persist()
}

type Rgb = [u8; 3];

const BACKGROUND: Rgb = [255, 255, 255];
const INK: Rgb = [0, 0, 0];
const FRAME: Rgb = [90, 90, 90];
const NOT_FINITE: Rgb = [128, 128, 128];

/// Margin around everything, in canvas pixels.
const PAD: usize = 12;
/// Font pixels are drawn as TEXT_SCALE x TEXT_SCALE squares.
const TEXT_SCALE: usize = 2;
const GLYPH_W: usize = 5;
const GLYPH_H: usize = 7;
const CHAR_ADVANCE: usize = (GLYPH_W + 1) * TEXT_SCALE;
const TEXT_H: usize = GLYPH_H * TEXT_SCALE;
const TITLE_GAP: usize = 10;
const BAR_GAP: usize = 16;
const BAR_W: usize = 20;
const BAR_MIN_H: usize = 96;
const TICK_LEN: usize = 5;
const LABEL_GAP: usize = 4;
/// Displayed images are enlarged to at least about this many pixels on their longer side...
const TARGET_DISPLAY: usize = 512;
/// ...and reduced when longer than this.
const MAX_DISPLAY: usize = 1024;
const MAX_ZOOM: usize = 32;

/// Where everything goes on the canvas.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Layout {
    /// Displayed pixels per image pixel (>= 1).
    zoom: usize,
    /// Image pixels per displayed block (>= 1).
    shrink: usize,
    /// Blocks across and down.
    blocks_x: usize,
    blocks_y: usize,
    image_x: usize,
    image_y: usize,
    image_w: usize,
    image_h: usize,
    bar_x: usize,
    bar_y: usize,
    bar_h: usize,
    label_x: usize,
    width: usize,
    height: usize,
}

fn layout(size_x: usize, size_y: usize, title_chars: usize, label_chars: usize) -> Layout {
    layout_with(size_x, size_y, title_chars, label_chars, false)
}

/// Characters of an axis tick label at most (offsets such as `-12.5`).
const AXIS_LABEL_CHARS: usize = 5;

/// The layout, with room for sky axes (offset ticks and labels left of and below the image,
/// and the axes' caption) where `axes`.
fn layout_with(size_x: usize, size_y: usize, title_chars: usize, label_chars: usize, axes: bool) -> Layout {
    let longer = size_x.max(size_y);
    let shrink = longer.div_ceil(MAX_DISPLAY).max(1);
    let zoom = if shrink > 1 { 1 } else { (TARGET_DISPLAY / longer).clamp(1, MAX_ZOOM) };
    let (blocks_x, blocks_y) = (size_x.div_ceil(shrink), size_y.div_ceil(shrink));
    let (image_w, image_h) = (blocks_x * zoom, blocks_y * zoom);
    let image_x = PAD + if axes { AXIS_LABEL_CHARS * CHAR_ADVANCE + TICK_LEN + LABEL_GAP } else { 0 };
    let image_y = PAD + TEXT_H + TITLE_GAP;
    let bar_x = image_x + image_w + BAR_GAP;
    let bar_h = image_h.max(BAR_MIN_H);
    let label_x = bar_x + BAR_W + TICK_LEN + LABEL_GAP;
    let width = (label_x + label_chars * CHAR_ADVANCE + PAD).max(2 * PAD + title_chars * CHAR_ADVANCE);
    // Labels are centred on ticks and may stand half a line beyond the bar's ends.
    let below = if axes { TICK_LEN + LABEL_GAP + 2 * TEXT_H + LABEL_GAP } else { 0 };
    let height = image_y + (image_h + below).max(bar_h) + TEXT_H / 2 + PAD;
    Layout { zoom, shrink, blocks_x, blocks_y, image_x, image_y, image_w, image_h, bar_x, bar_y: image_y, bar_h, label_x, width, height }
}

struct Canvas {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(width: usize, height: usize) -> Canvas {
        Canvas { width, height, rgb: BACKGROUND.repeat(width * height) }
    }

    fn set(&mut self, x: usize, y: usize, c: Rgb) {
        if x < self.width && y < self.height {
            let i = 3 * (y * self.width + x);
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    fn fill(&mut self, x: usize, y: usize, w: usize, h: usize, c: Rgb) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.set(xx, yy, c);
            }
        }
    }

    /// A one-pixel outline just outside the rectangle.
    fn frame(&mut self, x: usize, y: usize, w: usize, h: usize, c: Rgb) {
        let (x0, y0) = (x.saturating_sub(1), y.saturating_sub(1));
        for xx in x0..=x + w {
            self.set(xx, y0, c);
            self.set(xx, y + h, c);
        }
        for yy in y0..=y + h {
            self.set(x0, yy, c);
            self.set(x + w, yy, c);
        }
    }

    fn text(&mut self, x: usize, y: usize, text: &str, c: Rgb) {
        for (k, ch) in text.chars().enumerate() {
            let rows = glyph(ch);
            for (gy, bits) in rows.iter().enumerate() {
                for gx in 0..GLYPH_W {
                    if bits & (1 << (GLYPH_W - 1 - gx)) != 0 {
                        let px = x + k * CHAR_ADVANCE + gx * TEXT_SCALE;
                        self.fill(px, y + gy * TEXT_SCALE, TEXT_SCALE, TEXT_SCALE, c);
                    }
                }
            }
        }
    }
}

/// The mapping from pixel values to [0, 1] and the labelled ticks of the colour bar.
struct ColourScale {
    map: Box<dyn Fn(f64) -> Option<f64>>,
    palette: fn(f64) -> Rgb,
    /// `(position in [0, 1], label)`.
    ticks: Vec<(f64, String)>,
}

fn colour_scale(values: impl Iterator<Item = f64>, scale: PreviewScale) -> Result<ColourScale> {
    let (lo, hi) = values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let finite = |v: f64| v.is_finite().then_some(v);
    match scale {
        PreviewScale::Linear => {
            if !(hi > lo) {
                // Constant (or empty) image: one colour, one label.
                let value = if lo.is_finite() { lo } else { 0.0 };
                return Ok(ColourScale { map: Box::new(move |v| finite(v).map(|_| 0.5)), palette: colour, ticks: vec![(0.5, format_value(value))] });
            }
            let mut ticks = vec![(0.0, format_value(lo)), (1.0, format_value(hi))];
            let step = nice_step((hi - lo) / 5.0);
            let mut k = (lo / step).ceil();
            while k * step <= hi {
                let v = k * step;
                ticks.push(((v - lo) / (hi - lo), format_tick(v, step)));
                k += 1.0;
            }
            Ok(ColourScale { map: Box::new(move |v| finite(v).map(|v| (v - lo) / (hi - lo))), palette: colour, ticks })
        }
        PreviewScale::Log { dynamic_range } => {
            if !(dynamic_range > 1.0) || !dynamic_range.is_finite() {
                return Err(Error::parameter(
                    "dynamic_range",
                    format!("expected a finite dynamic range above 1 for the log scale, got {dynamic_range}"),
                ));
            }
            if !(hi > 0.0) {
                // Nothing positive to show on a log scale.
                return Ok(ColourScale { map: Box::new(move |v| finite(v).map(|_| 0.0)), palette: colour, ticks: vec![(0.0, "no positive pixel".into())] });
            }
            let decades = dynamic_range.log10();
            let floor = hi / dynamic_range;
            let position = move |v: f64| ((v.max(floor) / hi).log10() + decades) / decades;
            let mut ticks = vec![(0.0, format_value(floor)), (1.0, format_value(hi))];
            let (first, last) = (floor.log10().ceil() as i32, hi.log10().floor() as i32);
            // At most about eight decade ticks.
            let every = ((last - first + 1) as usize).div_ceil(8).max(1);
            for k in (first..=last).rev().step_by(every) {
                ticks.push((position(10f64.powi(k)), format_power_of_ten(k)));
            }
            Ok(ColourScale { map: Box::new(move |v| finite(v).map(position)), palette: colour, ticks })
        }
        PreviewScale::Signed { softening } => {
            let reach = lo.abs().max(hi.abs());
            if !(reach > 0.0) || !reach.is_finite() {
                return Ok(ColourScale { map: Box::new(move |v| finite(v).map(|_| 0.5)), palette: diverging, ticks: vec![(0.5, "0".into())] });
            }
            // A softening that is not positive (an image without noise) falls back to a
            // thousandth of the largest magnitude.
            let soft = if softening > 0.0 && softening.is_finite() { softening.min(reach) } else { reach * 1e-3 };
            let top = (reach / soft).asinh();
            let position = move |v: f64| 0.5 + 0.5 * (v / soft).asinh() / top;
            let mut ticks = vec![(0.5, "0".to_string()), (1.0, format_value(reach)), (0.0, format_value(-reach))];
            // Powers of ten between the softening and the largest magnitude, both signs.
            let (first, last) = ((soft.log10()).ceil() as i32, reach.log10().floor() as i32);
            let every = ((last - first + 1).max(1) as usize).div_ceil(4).max(1);
            for k in (first..=last).rev().step_by(every) {
                let v = 10f64.powi(k);
                ticks.push((position(v), format_power_of_ten(k)));
                ticks.push((position(-v), format!("-{}", format_power_of_ten(k))));
            }
            Ok(ColourScale { map: Box::new(move |v| finite(v).map(position)), palette: diverging, ticks })
        }
    }
}

/// The beam ellipse (lower left) and a scale bar (lower right) over the image area.
fn draw_sky(canvas: &mut Canvas, l: &Layout, sky: &SkyFrame) {
    if !(sky.pixel_arcsec > 0.0 && sky.pixel_arcsec.is_finite()) {
        return;
    }
    // Display pixels per arcsecond.
    let per_arcsec = l.zoom as f64 / (l.shrink as f64 * sky.pixel_arcsec);
    let margin = 8.0;
    if let Some((major, minor, pa)) = sky.beam {
        let (a, b) = (0.5 * major * per_arcsec, 0.5 * minor * per_arcsec);
        // A beam larger than a fifth of the image is left out rather than covering it.
        if a.is_finite() && b > 0.0 && a <= 0.2 * l.image_w.min(l.image_h) as f64 {
            let reach = a.max(2.0);
            let (cx, cy) = (l.image_x as f64 + margin + reach, (l.image_y + l.image_h) as f64 - margin - reach);
            // Position angle from north (up) towards east (left).
            let (s, c) = pa.to_radians().sin_cos();
            let r = reach.ceil() as i64 + 1;
            for dy in -r..=r {
                for dx in -r..=r {
                    let (x, y) = (dx as f64, dy as f64);
                    // Along the major axis: up rotated towards the left by pa.
                    let along = -x * s - y * c;
                    let across = x * c - y * s;
                    let q = (along / a.max(0.5)).powi(2) + (across / b.max(0.5)).powi(2);
                    if q <= 1.0 {
                        let inner = q <= 0.6;
                        let (px, py) = ((cx + x) as usize, (cy + y) as usize);
                        canvas.set(px, py, if inner { [200, 200, 200] } else { INK });
                    }
                }
            }
        }
    }
    // Scale bar: a round angle of about a fifth of the image width.
    let width_arcsec = l.image_w as f64 / per_arcsec;
    let target = 0.2 * width_arcsec;
    let (value, unit, arcsec) = if target >= 120.0 {
        let v = nice_floor(target / 60.0);
        (v, "arcmin", v * 60.0)
    } else {
        let v = nice_floor(target);
        (v, "arcsec", v)
    };
    let length = (arcsec * per_arcsec).round() as usize;
    if length >= 4 {
        let label = format!("{} {unit}", format_tick(value, value));
        let x1 = l.image_x + l.image_w - margin as usize;
        let x0 = x1.saturating_sub(length);
        let y = l.image_y + l.image_h - margin as usize - 1;
        canvas.fill(x0, y - 1, length, 3, INK);
        let text_w = label.chars().count() * CHAR_ADVANCE;
        // Centred over the bar, but kept inside the image: a label wider than the bar would
        // otherwise run past the image's right edge and be cut by the colour bar.
        let right = l.image_x + l.image_w;
        let tx = ((x0 + x1) / 2).saturating_sub(text_w / 2).min(right.saturating_sub(text_w + 3)).max(l.image_x + 2);
        canvas.fill(tx - 2, y - 4 - TEXT_H - 2, text_w + 4, TEXT_H + 4, BACKGROUND);
        canvas.text(tx, y - 4 - TEXT_H, &label, INK);
    }
}

/// Offset axes from the phase centre (the image's centre pixel, `N/2`): right ascension
/// growing to the left (east) below the image, declination growing up at its left, in
/// arcseconds or arcminutes for larger fields, with a caption naming them.
fn draw_axes(canvas: &mut Canvas, l: &Layout, size_x: usize, size_y: usize, sky: &SkyFrame) {
    if !(sky.pixel_arcsec > 0.0 && sky.pixel_arcsec.is_finite()) {
        return;
    }
    let field = size_x.max(size_y) as f64 * sky.pixel_arcsec;
    let (unit, per_unit) = if field > 600.0 { ("arcmin", 60.0) } else { ("arcsec", 1.0) };
    let step = nice_step(field / per_unit / 5.0);
    // Display position of image pixel coordinate `p` (0-based, pixel centres) along an axis.
    let display = |p: f64| (p + 0.5) * l.zoom as f64 / l.shrink as f64;
    let ticks = |n: usize| -> Vec<(f64, f64)> {
        let half = n as f64 / 2.0 * sky.pixel_arcsec / per_unit;
        let k_max = (half / step).floor() as i64;
        (-k_max..=k_max).map(|k| (k as f64 * step, k as f64 * step * per_unit / sky.pixel_arcsec)).collect()
    };
    let y_axis = l.image_y + l.image_h;
    for (value, pixels) in ticks(size_x) {
        // East (positive RA offset) to the left of the centre pixel.
        let x = display(size_x as f64 / 2.0 - pixels);
        if x < 0.0 || x >= l.image_w as f64 {
            continue;
        }
        let x = l.image_x + x as usize;
        canvas.fill(x, y_axis + 1, 1, TICK_LEN, INK);
        let label = format_tick(value, step);
        let w = label.chars().count() * CHAR_ADVANCE;
        canvas.text(x.saturating_sub(w / 2), y_axis + 1 + TICK_LEN + LABEL_GAP, &label, INK);
    }
    for (value, pixels) in ticks(size_y) {
        let y = display(size_y as f64 / 2.0 + pixels);
        if y < 0.0 || y >= l.image_h as f64 {
            continue;
        }
        let y = l.image_y + l.image_h - 1 - y as usize;
        canvas.fill(l.image_x.saturating_sub(1 + TICK_LEN), y, TICK_LEN, 1, INK);
        let label = format_tick(value, step);
        let w = label.chars().count() * CHAR_ADVANCE;
        canvas.text(l.image_x.saturating_sub(1 + TICK_LEN + LABEL_GAP + w), y.saturating_sub(TEXT_H / 2), &label, INK);
    }
    let caption = format!("RA, Dec offset ({unit}), east left");
    canvas.text(l.image_x, y_axis + 1 + TICK_LEN + 2 * LABEL_GAP + TEXT_H, &caption, INK);
}

/// 1, 2 or 5 times a power of ten, at most `raw`.
fn nice_floor(raw: f64) -> f64 {
    let magnitude = 10f64.powf(raw.log10().floor());
    [5.0, 2.0, 1.0].iter().map(|m| m * magnitude).find(|&s| s <= raw * (1.0 + 1e-12)).unwrap_or(magnitude)
}

/// 1, 2 or 5 times a power of ten, at least `raw`.
fn nice_step(raw: f64) -> f64 {
    let magnitude = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * magnitude).find(|&s| s >= raw * (1.0 - 1e-12)).unwrap_or(10.0 * magnitude)
}

/// Three significant digits, scientific outside [1e-3, 1e4).
fn format_value(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    // The exponent after rounding to three digits, so that 0.99996 reads 1.00, not 1.000.
    let scientific = format!("{v:.2e}");
    let exponent: i32 = scientific.rsplit('e').next().and_then(|e| e.parse().ok()).unwrap_or(0);
    if (-3..4).contains(&exponent) {
        format!("{:.*}", (2 - exponent).max(0) as usize, v)
    } else {
        scientific
    }
}

/// A tick on a grid of `step`: as many decimals as the step needs.
fn format_tick(v: f64, step: f64) -> String {
    if v.abs() < 1e-9 * step {
        return "0".into();
    }
    let decimals = -step.log10().floor() as i32;
    if (-3..=3).contains(&decimals) && v.abs() < 1e5 {
        format!("{:.*}", decimals.max(0) as usize, v)
    } else {
        format!("{v:.1e}")
    }
}

fn format_power_of_ten(k: i32) -> String {
    match k {
        -2..=0 => format!("{}", 10f64.powi(k)),
        1..=3 => format!("{}", 10i64.pow(k as u32)),
        _ => format!("1e{k}"),
    }
}

/// Draws the preview in memory.
fn render(image: &[f64], size_x: usize, size_y: usize, scale: PreviewScale, title: &str, sky: Option<&SkyFrame>) -> Result<Canvas> {
    if size_x == 0 || size_y == 0 || image.len() != size_x * size_y {
        return Err(Error::parameter(
            "image",
            format!("expected {size_x} x {size_y} = {} pixels (both sizes > 0), got {}", size_x * size_y, image.len()),
        ));
    }
    let probe = layout(size_x, size_y, 0, 0);
    let reduce = |bx: usize, by: usize| -> f64 {
        let s = probe.shrink;
        if s == 1 {
            return image[by * size_x + bx];
        }
        let mut best = f64::NAN;
        for iy in by * s..((by + 1) * s).min(size_y) {
            for &v in &image[iy * size_x + bx * s..iy * size_x + ((bx + 1) * s).min(size_x)] {
                let better = match scale {
                    PreviewScale::Linear | PreviewScale::Signed { .. } => v.abs() > best.abs() || best.is_nan(),
                    PreviewScale::Log { .. } => v > best || best.is_nan(),
                };
                if v.is_finite() && better {
                    best = v;
                }
            }
        }
        best
    };
    let blocks: Vec<f64> = (0..probe.blocks_y).flat_map(|by| (0..probe.blocks_x).map(move |bx| (bx, by))).map(|(bx, by)| reduce(bx, by)).collect();
    let colours = colour_scale(blocks.iter().copied(), scale)?;
    let label_chars = colours.ticks.iter().map(|t| t.1.chars().count()).max().unwrap_or(0);
    let l = layout_with(size_x, size_y, title.chars().count(), label_chars, sky.is_some());
    let mut canvas = Canvas::new(l.width, l.height);

    canvas.text(PAD, PAD, title, INK);

    // Image: display row 0 is the top, i.e. the highest block row (north up); block column 0
    // (lowest ix, east) on the left.
    for row in 0..l.blocks_y {
        let by = l.blocks_y - 1 - row;
        for bx in 0..l.blocks_x {
            let c = (colours.map)(blocks[by * l.blocks_x + bx]).map_or(NOT_FINITE, colours.palette);
            canvas.fill(l.image_x + bx * l.zoom, l.image_y + row * l.zoom, l.zoom, l.zoom, c);
        }
    }
    canvas.frame(l.image_x, l.image_y, l.image_w, l.image_h, FRAME);
    if let Some(sky) = sky {
        draw_sky(&mut canvas, &l, sky);
        draw_axes(&mut canvas, &l, size_x, size_y, sky);
    }

    // Colour bar, top colour at the top.
    for y in 0..l.bar_h {
        let t = 1.0 - y as f64 / (l.bar_h - 1) as f64;
        canvas.fill(l.bar_x, l.bar_y + y, BAR_W, 1, (colours.palette)(t));
    }
    canvas.frame(l.bar_x, l.bar_y, BAR_W, l.bar_h, FRAME);
    let tick_y = |t: f64| l.bar_y + ((1.0 - t) * (l.bar_h - 1) as f64).round() as usize;
    let mut placed: Vec<usize> = Vec::new();
    // End labels first, then inner ticks that keep clear of the labels already placed.
    for (t, label) in &colours.ticks {
        let y = tick_y(*t);
        if placed.iter().any(|&p| p.abs_diff(y) < TEXT_H + 2) {
            continue;
        }
        placed.push(y);
        canvas.fill(l.bar_x + BAR_W, y, TICK_LEN, 1, INK);
        canvas.text(l.label_x, y.saturating_sub(TEXT_H / 2), label, INK);
    }
    Ok(canvas)
}

/// Viridis (matplotlib, CC0) sampled every 8th of its 256 entries, plus the last one.
const VIRIDIS: [Rgb; 33] = [
    [68, 1, 84], [71, 13, 96], [72, 24, 106], [72, 35, 116], [71, 45, 123], [69, 55, 129], [66, 64, 134],
    [62, 73, 137], [59, 82, 139], [55, 91, 141], [51, 99, 141], [47, 107, 142], [44, 114, 142], [41, 122, 142],
    [38, 130, 142], [35, 137, 142], [33, 145, 140], [31, 152, 139], [31, 160, 136], [34, 167, 133], [40, 174, 128],
    [50, 182, 122], [63, 188, 115], [78, 195, 107], [94, 201, 98], [112, 207, 87], [132, 212, 75], [152, 216, 62],
    [173, 220, 48], [194, 223, 35], [216, 226, 25], [236, 229, 27], [253, 231, 37],
];

/// Viridis at `t` in [0, 1] (clamped), interpolated linearly between the anchors (within 2/255
/// of the full table). Anchor k sits at entry 8k of 256, the last one at entry 255.
fn colour(t: f64) -> Rgb {
    let entry = t.clamp(0.0, 1.0) * 255.0;
    let k = ((entry / 8.0).floor() as usize).min(VIRIDIS.len() - 2);
    let (a, b) = ((8 * k) as f64, ((8 * k + 8).min(255)) as f64);
    let f = ((entry - a) / (b - a)).clamp(0.0, 1.0);
    let (c0, c1) = (VIRIDIS[k], VIRIDIS[k + 1]);
    [0, 1, 2].map(|i| (c0[i] as f64 + f * (c1[i] as f64 - c0[i] as f64)).round() as u8)
}

/// A diverging palette for signed images: dark blue (most negative) through white (zero, at
/// 0.5) to dark red (most positive), the anchors of ColorBrewer's RdBu (Apache-2.0), reversed.
const RDBU: [Rgb; 11] = [
    [5, 48, 97], [33, 102, 172], [67, 147, 195], [146, 197, 222], [209, 229, 240], [247, 247, 247],
    [253, 219, 199], [244, 165, 130], [214, 96, 77], [178, 24, 43], [103, 0, 31],
];

fn diverging(t: f64) -> Rgb {
    let x = t.clamp(0.0, 1.0) * (RDBU.len() - 1) as f64;
    let k = (x.floor() as usize).min(RDBU.len() - 2);
    let f = x - k as f64;
    let (c0, c1) = (RDBU[k], RDBU[k + 1]);
    [0, 1, 2].map(|i| (c0[i] as f64 + f * (c1[i] as f64 - c0[i] as f64)).round() as u8)
}

/// 5 x 7 glyphs, one byte per row (top first), bit 4 the leftmost column. Lower-case letters
/// have their own shapes; anything unknown is drawn as '?'.
fn glyph(c: char) -> [u8; 7] {
    match c {
        ' ' => [0, 0, 0, 0, 0, 0, 0],
        '0' => [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110],
        '1' => [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
        '2' => [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111],
        '3' => [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110],
        '4' => [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010],
        '5' => [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110],
        '6' => [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110],
        '7' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000],
        '8' => [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110],
        '9' => [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100],
        'A' => [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001],
        'B' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110],
        'C' => [0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110],
        'D' => [0b11100, 0b10010, 0b10001, 0b10001, 0b10001, 0b10010, 0b11100],
        'E' => [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111],
        'F' => [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000],
        'G' => [0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111],
        'H' => [0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001],
        'I' => [0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
        'J' => [0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100],
        'K' => [0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001],
        'L' => [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111],
        'M' => [0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001],
        'N' => [0b10001, 0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001],
        'O' => [0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110],
        'P' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000],
        'Q' => [0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101],
        'R' => [0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001],
        'S' => [0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110],
        'T' => [0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100],
        'U' => [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110],
        'V' => [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100],
        'W' => [0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010],
        'X' => [0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001],
        'Y' => [0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100],
        'Z' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111],
        'a' => [0, 0, 0b01110, 0b00001, 0b01111, 0b10001, 0b01111],
        'b' => [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b11110],
        'c' => [0, 0, 0b01110, 0b10000, 0b10000, 0b10001, 0b01110],
        'd' => [0b00001, 0b00001, 0b01101, 0b10011, 0b10001, 0b10001, 0b01111],
        'e' => [0, 0, 0b01110, 0b10001, 0b11111, 0b10000, 0b01110],
        'f' => [0b00110, 0b01001, 0b01000, 0b11100, 0b01000, 0b01000, 0b01000],
        'g' => [0, 0, 0b01111, 0b10001, 0b01111, 0b00001, 0b01110],
        'h' => [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001],
        'i' => [0b00100, 0, 0b01100, 0b00100, 0b00100, 0b00100, 0b01110],
        'j' => [0b00010, 0, 0b00110, 0b00010, 0b00010, 0b10010, 0b01100],
        'k' => [0b10000, 0b10000, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010],
        'l' => [0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
        'm' => [0, 0, 0b11010, 0b10101, 0b10101, 0b10001, 0b10001],
        'n' => [0, 0, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001],
        'o' => [0, 0, 0b01110, 0b10001, 0b10001, 0b10001, 0b01110],
        'p' => [0, 0, 0b11110, 0b10001, 0b11110, 0b10000, 0b10000],
        'q' => [0, 0, 0b01101, 0b10011, 0b01111, 0b00001, 0b00001],
        'r' => [0, 0, 0b10110, 0b11001, 0b10000, 0b10000, 0b10000],
        's' => [0, 0, 0b01110, 0b10000, 0b01110, 0b00001, 0b11110],
        't' => [0b01000, 0b01000, 0b11100, 0b01000, 0b01000, 0b01001, 0b00110],
        'u' => [0, 0, 0b10001, 0b10001, 0b10001, 0b10011, 0b01101],
        'v' => [0, 0, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100],
        'w' => [0, 0, 0b10001, 0b10001, 0b10101, 0b10101, 0b01010],
        'x' => [0, 0, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001],
        'y' => [0, 0, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110],
        'z' => [0, 0, 0b11111, 0b00010, 0b00100, 0b01000, 0b11111],
        '.' => [0, 0, 0, 0, 0, 0b01100, 0b01100],
        ',' => [0, 0, 0, 0, 0b01100, 0b00100, 0b01000],
        ':' => [0, 0b01100, 0b01100, 0, 0b01100, 0b01100, 0],
        ';' => [0, 0b01100, 0b01100, 0, 0b01100, 0b00100, 0b01000],
        '-' => [0, 0, 0, 0b11111, 0, 0, 0],
        '+' => [0, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0],
        '=' => [0, 0, 0b11111, 0, 0b11111, 0, 0],
        '/' => [0, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0],
        '(' => [0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010],
        ')' => [0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000],
        '[' => [0b01110, 0b01000, 0b01000, 0b01000, 0b01000, 0b01000, 0b01110],
        ']' => [0b01110, 0b00010, 0b00010, 0b00010, 0b00010, 0b00010, 0b01110],
        '<' => [0b00010, 0b00100, 0b01000, 0b10000, 0b01000, 0b00100, 0b00010],
        '>' => [0b01000, 0b00100, 0b00010, 0b00001, 0b00010, 0b00100, 0b01000],
        '_' => [0, 0, 0, 0, 0, 0, 0b11111],
        '%' => [0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011],
        '*' => [0, 0b00100, 0b10101, 0b01110, 0b10101, 0b00100, 0],
        '^' => [0b00100, 0b01010, 0b10001, 0, 0, 0, 0],
        '\'' => [0b01100, 0b00100, 0b01000, 0, 0, 0, 0],
        '"' => [0b01010, 0b01010, 0b01010, 0, 0, 0, 0],
        '#' => [0b01010, 0b01010, 0b11111, 0b01010, 0b11111, 0b01010, 0b01010],
        '!' => [0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0b00100],
        '|' => [0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100],
        _ => [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0, 0b00100],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sky_previews_have_offset_axes_a_beam_and_a_scale_bar() {
        let n = 64;
        let image: Vec<f64> = (0..n * n).map(|k| ((k % n) as f64 - 32.0) * 0.01).collect();
        let sky = SkyFrame { pixel_arcsec: 2.0, beam: Some((8.0, 4.0, 30.0)) };
        let plain = render(&image, n, n, PreviewScale::Signed { softening: 0.01 }, "t", None).unwrap();
        let framed = render(&image, n, n, PreviewScale::Signed { softening: 0.01 }, "t", Some(&sky)).unwrap();
        let l = layout_with(n, n, 1, 5, true);
        assert!(framed.width > plain.width && framed.height > plain.height, "room for the axes");
        let ink = |c: &Canvas, x0: usize, y0: usize, w: usize, h: usize| {
            (y0..y0 + h).flat_map(|y| (x0..x0 + w).map(move |x| (x, y))).filter(|&(x, y)| c.rgb[3 * (y * c.width + x)..3 * (y * c.width + x) + 3] == INK).count()
        };
        // Ticks and labels below and left of the image; a beam in its lower left corner (the
        // signed palette has no black, so ink inside the image is the overlay's).
        assert!(ink(&framed, l.image_x, l.image_y + l.image_h + 1, l.image_w, TICK_LEN + LABEL_GAP + TEXT_H) > 20);
        assert!(ink(&framed, PAD, l.image_y, l.image_x - PAD, l.image_h) > 20);
        assert!((0..=100).all(|k| diverging(k as f64 / 100.0) != INK));
        assert!(ink(&framed, l.image_x, l.image_y + l.image_h / 2, l.image_w / 3, l.image_h / 2) > 0);
        // The scale bar's label stays inside the image, however much wider than the bar it is.
        for (n, pixel_arcsec) in [(16, 0.001), (32, 0.013), (64, 2.0), (512, 0.3)] {
            let image: Vec<f64> = (0..n * n).map(|k| ((k % n) as f64 - n as f64 / 2.0) * 0.01).collect();
            let sky = SkyFrame { pixel_arcsec, beam: None };
            let framed = render(&image, n, n, PreviewScale::Signed { softening: 0.01 }, "t", Some(&sky)).unwrap();
            let l = layout_with(n, n, 1, 5, true);
            let inside = ink(&framed, l.image_x + l.image_w / 2, l.image_y + l.image_h / 2, l.image_w / 2, l.image_h / 2);
            let beyond = ink(&framed, l.image_x + l.image_w, l.image_y, l.bar_x - l.image_x - l.image_w, l.image_h);
            assert!(inside > 0 && beyond == 0, "{n} px of {pixel_arcsec} arcsec: label ink {inside} inside, {beyond} beyond the image");
        }
    }

    #[test]
    fn the_signed_scale_puts_zero_at_white_and_negatives_in_blue() {
        let cs = colour_scale([-2.0, 0.0, 1.0, 0.01].into_iter(), PreviewScale::Signed { softening: 0.01 }).unwrap();
        assert_eq!((cs.map)(0.0), Some(0.5));
        let (neg, pos) = ((cs.map)(-0.01).unwrap(), (cs.map)(0.01).unwrap());
        assert!(neg < 0.5 && pos > 0.5 && ((0.5 - neg) - (pos - 0.5)).abs() < 1e-12);
        assert_eq!((cs.map)(-2.0), Some(0.0));
        assert_eq!((cs.map)(2.0), Some(1.0));
        assert_eq!((cs.palette)(0.5), [247, 247, 247]);
        let (blue, red) = ((cs.palette)(neg), (cs.palette)(pos));
        assert!(blue[2] > blue[0] && red[0] > red[2], "{blue:?} {red:?}");
        // Asinh: linear near zero, logarithmic far out (a tenfold value is far less than ten
        // times further from white).
        let step = |v: f64| (cs.map)(v).unwrap() - 0.5;
        assert!((step(0.001) / step(0.0005) - 2.0).abs() < 0.01);
        assert!(step(1.0) / step(0.1) < 2.0);
        assert!(cs.ticks.iter().any(|(_, l)| l == "-0.1") && cs.ticks.iter().any(|(_, l)| l == "0"));
    }

    const TOP: Rgb = [253, 231, 37];
    const BOTTOM: Rgb = [68, 1, 84];

    struct Decoded {
        width: usize,
        height: usize,
        rgb: Vec<u8>,
    }

    impl Decoded {
        fn at(&self, x: usize, y: usize) -> Rgb {
            let i = 3 * (y * self.width + x);
            [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
        }
    }

    fn decode(path: &Path) -> Decoded {
        let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        buf.truncate(info.buffer_size());
        Decoded { width: info.width as usize, height: info.height as usize, rgb: buf }
    }

    /// A 64 x 48 test image: a faint gradient, one bright pixel near the top-left (north-east)
    /// and the minimum at the bottom-right corner.
    fn test_image() -> (Vec<f64>, usize, usize) {
        let (nx, ny) = (64, 48);
        let mut img: Vec<f64> = (0..nx * ny).map(|i| 0.1 + 0.3 * ((i % nx) as f64 / nx as f64)).collect();
        img[40 * nx + 10] = 5.0;
        img[63] = -1.0; // (ix 63, iy 0)
        (img, nx, ny)
    }

    fn display_block(l: &Layout, ix: usize, iy: usize) -> (usize, usize) {
        (l.image_x + ix * l.zoom, l.image_y + (l.blocks_y - 1 - iy) * l.zoom)
    }

    #[test]
    fn png_decodes_with_north_up_and_east_left() {
        let dir = tempfile::tempdir().unwrap();
        let (img, nx, ny) = test_image();
        for scale in [PreviewScale::Linear, PreviewScale::Log { dynamic_range: 1e3 }] {
            let path = dir.path().join("preview.png");
            write_png(&path, &img, nx, ny, scale, "Test image (Jy/beam)").unwrap();
            let png = decode(&path);
            let ticks = colour_scale(img.iter().copied(), scale).unwrap().ticks;
            let label_chars = ticks.iter().map(|t| t.1.len()).max().unwrap();
            let l = layout(nx, ny, "Test image (Jy/beam)".len(), label_chars);
            assert_eq!((png.width, png.height), (l.width, l.height));
            assert_eq!(l.zoom, 8);
            assert_eq!((l.image_w, l.image_h), (512, 384));
            // The bright pixel (ix 10, iy 40) is near the top left, in the top colour.
            let (x, y) = display_block(&l, 10, 40);
            assert_eq!((x, y), (l.image_x + 80, l.image_y + 7 * 8));
            for dy in 0..l.zoom {
                for dx in 0..l.zoom {
                    assert_eq!(png.at(x + dx, y + dy), TOP, "{scale:?}");
                }
            }
            // Its unflipped position holds an ordinary pixel.
            let (ux, uy) = (l.image_x + 10 * l.zoom, l.image_y + 40 * l.zoom);
            assert_ne!(png.at(ux, uy), TOP);
            // Only that block has the top colour inside the image.
            let tops = (l.image_y..l.image_y + l.image_h)
                .flat_map(|y| (l.image_x..l.image_x + l.image_w).map(move |x| (x, y)))
                .filter(|&(x, y)| png.at(x, y) == TOP)
                .count();
            assert_eq!(tops, l.zoom * l.zoom);
            // The minimum (ix 63, iy 0) is at the bottom right in the bottom colour.
            let (x, y) = display_block(&l, 63, 0);
            assert_eq!((x + l.zoom, y + l.zoom), (l.image_x + l.image_w, l.image_y + l.image_h));
            assert_eq!(png.at(x, y), BOTTOM);
            // The colour bar runs from the top colour down to the bottom colour.
            let bx = l.bar_x + BAR_W / 2;
            assert_eq!(png.at(bx, l.bar_y), TOP);
            assert_eq!(png.at(bx, l.bar_y + l.bar_h - 1), BOTTOM);
            // Title and labels are drawn in ink.
            let ink = |x0: usize, x1: usize, y0: usize, y1: usize| {
                (y0..y1).flat_map(|y| (x0..x1).map(move |x| (x, y))).filter(|&(x, y)| png.at(x, y) == INK).count()
            };
            assert!(ink(PAD, l.width, PAD, PAD + TEXT_H) > 100, "title");
            assert!(ink(l.label_x, l.width, l.bar_y, l.bar_y + l.bar_h) > 100, "labels");
        }
    }

    #[test]
    fn log_scale_clips_below_peak_over_dynamic_range() {
        let scale = colour_scale([1e-6, 2e-3, 2.0].into_iter(), PreviewScale::Log { dynamic_range: 1e3 }).unwrap();
        let t = |v: f64| (scale.map)(v).unwrap();
        assert_eq!(t(2.0), 1.0);
        assert!((t(2e-3) - 0.0).abs() < 1e-12);
        assert_eq!(t(1e-6), 0.0);
        assert_eq!(t(-5.0), 0.0);
        assert!((t(2e-1) - 2.0 / 3.0).abs() < 1e-12);
        assert!((scale.map)(f64::NAN).is_none());
        let labels: Vec<&str> = scale.ticks.iter().map(|t| t.1.as_str()).collect();
        assert_eq!(labels, ["0.00200", "2.00", "1", "0.1", "0.01"]);
        let err = colour_scale([1.0].into_iter(), PreviewScale::Log { dynamic_range: 0.5 }).err().unwrap().to_string();
        assert!(err.contains("dynamic_range"), "{err}");
    }

    #[test]
    fn linear_ticks_are_round_numbers_inside_the_range() {
        let scale = colour_scale([-0.013, 0.0, 0.047].into_iter(), PreviewScale::Linear).unwrap();
        let labels: Vec<&str> = scale.ticks.iter().map(|t| t.1.as_str()).collect();
        assert_eq!(labels, ["-0.0130", "0.0470", "0", "0.02", "0.04"]);
        assert!(scale.ticks.iter().all(|t| (0.0..=1.0).contains(&t.0)));
        assert_eq!(format_value(12345.0), "1.23e4");
        assert_eq!(format_value(0.5), "0.500");
        assert_eq!(format_value(0.99996), "1.00");
        assert_eq!(format_value(-9999.7), "-1.00e4");
    }

    #[test]
    fn constant_and_non_finite_images_do_not_crash() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("flat.png");
        for scale in [PreviewScale::Linear, PreviewScale::Log { dynamic_range: 100.0 }] {
            for value in [0.0, 3.0, -2.0, f64::NAN] {
                write_png(&path, &vec![value; 20 * 10], 20, 10, scale, "flat").unwrap();
                let png = decode(&path);
                let l = layout(20, 10, 4, 0);
                assert!(png.width >= l.width && png.height == l.height);
            }
        }
    }

    #[test]
    fn large_images_are_reduced_keeping_point_sources() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.png");
        let (nx, ny) = (2100, 1500);
        let mut img = vec![0.0; nx * ny];
        img[1234 * nx + 2051] = 1.0;
        write_png(&path, &img, nx, ny, PreviewScale::Log { dynamic_range: 1e4 }, "big").unwrap();
        let png = decode(&path);
        let l = layout(nx, ny, 3, 0);
        assert_eq!((l.shrink, l.zoom, l.blocks_x, l.blocks_y), (3, 1, 700, 500));
        let (x, y) = display_block(&l, 2051 / 3, 1234 / 3);
        assert_eq!(png.at(x, y), TOP);
    }

    #[test]
    fn missing_directory_is_an_error_naming_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no/such/dir/preview.png");
        let err = write_png(&path, &[1.0; 64], 8, 8, PreviewScale::Linear, "x").unwrap_err().to_string();
        assert!(err.contains(&path.display().to_string()), "{err}");
        let err = write_png(&dir.path().join("a.png"), &[1.0; 63], 8, 8, PreviewScale::Linear, "x").unwrap_err().to_string();
        assert!(err.contains("8 x 8"), "{err}");
        // Nothing left behind in the directory after a failure.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn colour_map_ends_and_glyphs() {
        assert_eq!(colour(1.0), TOP);
        assert_eq!(colour(0.0), BOTTOM);
        assert_eq!(colour(2.0), TOP);
        // Viridis entry 128 is (0.127568, 0.566949, 0.550556).
        assert_eq!(colour(128.0 / 255.0), [33, 145, 140]);
        for c in "0123456789.-e+ /()ABCXYZabcxyz".chars() {
            assert_ne!(glyph(c), glyph('\u{1}'), "{c:?} has its own glyph");
        }
    }
}
