//! An RGB picture and the few things drawn on it.

use crate::RenderError;

/// An 8-bit RGB picture, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

impl Image {
    pub(crate) fn new(width: u32, height: u32, fill: [u8; 3]) -> Self {
        Self {
            width,
            height,
            rgb: fill.repeat(width as usize * height as usize),
        }
    }

    /// Width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The colour at (column, row).
    pub fn get(&self, c: u32, r: u32) -> [u8; 3] {
        let k = 3 * (r as usize * self.width as usize + c as usize);
        [self.rgb[k], self.rgb[k + 1], self.rgb[k + 2]]
    }

    /// Sets a pixel; outside the picture nothing happens.
    pub(crate) fn put(&mut self, c: i64, r: i64, colour: [u8; 3]) {
        if c >= 0 && r >= 0 && c < i64::from(self.width) && r < i64::from(self.height) {
            let k = 3 * (r as usize * self.width as usize + c as usize);
            self.rgb[k..k + 3].copy_from_slice(&colour);
        }
    }

    /// A one-pixel line (sampled at every pixel step along its longer axis).
    pub(crate) fn line(&mut self, a: (f32, f32), b: (f32, f32), colour: [u8; 3]) {
        let steps = (b.0 - a.0)
            .abs()
            .max((b.1 - a.1).abs())
            .ceil()
            .min(20_000.0) as i64;
        for k in 0..=steps.max(1) {
            let t = k as f32 / steps.max(1) as f32;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            self.put(x.round() as i64, y.round() as i64, colour);
        }
    }

    /// Text in an 8 × 8 font, `scale` pixels per font pixel, top left at (c, r); returns
    /// the width drawn, pixels.
    pub(crate) fn text(&mut self, s: &str, c: i64, r: i64, scale: i64, colour: [u8; 3]) -> i64 {
        let mut k = 0;
        for ch in s.chars() {
            let Some(&rows) = font8x8::legacy::BASIC_LEGACY.get(ch as usize) else {
                continue;
            };
            let x0 = c + k * 8 * scale;
            k += 1;
            for (dy, bits) in rows.iter().enumerate() {
                // Bit 0 is the leftmost column.
                for dx in 0..8 {
                    if bits & (1 << dx) != 0 {
                        for sy in 0..scale {
                            for sx in 0..scale {
                                self.put(x0 + dx * scale + sx, r + dy as i64 * scale + sy, colour);
                            }
                        }
                    }
                }
            }
        }
        k * 8 * scale
    }

    /// A filled rectangle, top left (c, r), clipped to the picture.
    pub(crate) fn fill(&mut self, c: i64, r: i64, w: i64, h: i64, colour: [u8; 3]) {
        for y in r..r + h {
            for x in c..c + w {
                self.put(x, y, colour);
            }
        }
    }

    /// The picture as PNG bytes.
    pub fn to_png(&self) -> Result<Vec<u8>, RenderError> {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc
            .write_header()
            .map_err(|e| RenderError::Png(e.to_string()))?;
        w.write_image_data(&self.rgb)
            .map_err(|e| RenderError::Png(e.to_string()))?;
        w.finish().map_err(|e| RenderError::Png(e.to_string()))?;
        Ok(out)
    }
}
