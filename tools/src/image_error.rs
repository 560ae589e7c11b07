//! Image error against a reference, as the flythrough and the tests report it.

/// Mean squared error over RGB between two images of the same size.
pub fn mse(a: &image::RgbaImage, b: &image::RgbaImage) -> f64 {
    let mut sum = 0.0f64;
    let mut n = 0u64;
    for (p, q) in a.pixels().zip(b.pixels()) {
        for c in 0..3 {
            let d = f64::from(p.0[c]) - f64::from(q.0[c]);
            sum += d * d;
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// Peak signal-to-noise ratio of `a` against `b` over RGB, in dB (∞ when equal).
pub fn psnr_db(a: &image::RgbaImage, b: &image::RgbaImage) -> f64 {
    let mse = mse(a, b);
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_a_known_difference() {
        let a = image::RgbaImage::from_pixel(4, 4, image::Rgba([10, 20, 30, 255]));
        let mut b = a.clone();
        assert_eq!(psnr_db(&a, &b), f64::INFINITY);
        // One channel of one pixel off by 48: MSE 48² / 48 = 48.
        b.put_pixel(0, 0, image::Rgba([58, 20, 30, 0]));
        assert!((mse(&a, &b) - 48.0).abs() < 1e-12);
        assert!((psnr_db(&a, &b) - 10.0 * (65025.0f64 / 48.0).log10()).abs() < 1e-12);
    }
}
