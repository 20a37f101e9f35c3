//! Product images as PNG for the status page and clients: DoLP in grey (0 black, 1 white),
//! AoP as hue around the colour wheel (-90 deg to 90 deg, the period of the orientation), S0
//! in grey from its 1st to its 99th percentile; undefined pixels (NaN) transparent.

use crate::runner::Plane;

/// The products served, by their URL names, and the store's names.
pub const PRODUCTS: [(&str, &str); 3] = [("s0", "s0"), ("dolp", "dolp"), ("aop", "aop_rad")];

/// RGBA of the hue `h` in [0, 1) at full saturation and value.
fn hue(h: f32) -> [u8; 4] {
    let x = (h.rem_euclid(1.0)) * 6.0;
    let f = x - x.floor();
    let (r, g, b) = match x as u32 {
        0 => (1.0, f, 0.0),
        1 => (1.0 - f, 1.0, 0.0),
        2 => (0.0, 1.0, f),
        3 => (0.0, 1.0 - f, 1.0),
        4 => (f, 0.0, 1.0),
        _ => (1.0, 0.0, 1.0 - f),
    };
    let q = |v: f32| (v * 255.0).round() as u8;
    [q(r), q(g), q(b), 255]
}

fn grey(v: f32) -> [u8; 4] {
    let g = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    [g, g, g, 255]
}

/// The `p`th percentile of the finite values (0 if none).
fn percentile(values: &[f32], p: f64) -> f32 {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// The PNG of product `name` (`s0`, `dolp` or `aop`).
pub fn render(name: &str, plane: &Plane) -> Result<Vec<u8>, String> {
    let (lo, hi) = match name {
        "s0" => (
            percentile(&plane.values, 0.01),
            percentile(&plane.values, 0.99),
        ),
        _ => (0.0, 1.0),
    };
    let span = (hi - lo).max(f32::EPSILON);
    let mut rgba = Vec::with_capacity(plane.values.len() * 4);
    for &v in &plane.values {
        let px = if !v.is_finite() {
            [0, 0, 0, 0]
        } else {
            match name {
                "aop" => hue((v / std::f32::consts::PI) + 0.5),
                "s0" => grey((v - lo) / span),
                _ => grey(v),
            }
        };
        rgba.extend_from_slice(&px);
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, plane.width, plane.height);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| e.to_string())?;
        w.write_image_data(&rgba).map_err(|e| e.to_string())?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aop_ends_meet_and_nan_is_transparent() {
        let half_pi = std::f32::consts::FRAC_PI_2;
        // -90 deg and +90 deg are the same orientation: the same colour.
        assert_eq!(
            hue(-half_pi / std::f32::consts::PI + 0.5),
            hue(half_pi / std::f32::consts::PI + 0.5)
        );
        let plane = Plane {
            width: 2,
            height: 1,
            set: 0,
            values: vec![f32::NAN, 0.5],
        };
        let png = render("dolp", &plane).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        assert_eq!(&buf[..8], &[0, 0, 0, 0, 128, 128, 128, 255]);
    }
}
