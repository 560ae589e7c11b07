//! WGS 84 Earth-centred coordinates (EPSG:4978) and local east-north-up frames.

/// WGS 84 semi-major axis in metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS 84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// WGS 84 semi-minor axis in metres.
pub const WGS84_B: f64 = WGS84_A * (1.0 - WGS84_F);

/// Geodetic latitude and longitude (radians) and ellipsoidal height (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Geodetic {
    pub latitude: f64,
    pub longitude: f64,
    pub height: f64,
}

/// Earth-centred, Earth-fixed coordinates of a geodetic position.
pub fn to_ecef(g: Geodetic) -> [f64; 3] {
    let e2 = WGS84_F * (2.0 - WGS84_F);
    let (sin_lat, cos_lat) = g.latitude.sin_cos();
    let (sin_lon, cos_lon) = g.longitude.sin_cos();
    let n = WGS84_A / (1.0 - e2 * sin_lat * sin_lat).sqrt();
    [
        (n + g.height) * cos_lat * cos_lon,
        (n + g.height) * cos_lat * sin_lon,
        (n * (1.0 - e2) + g.height) * sin_lat,
    ]
}

/// The geodetic position of an Earth-centred point (Bowring's iteration, to well below a
/// millimetre anywhere near the surface); `None` near the Earth's centre or for
/// coordinates that are not finite.
pub fn to_geodetic(p: [f64; 3]) -> Option<Geodetic> {
    if p.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let e2 = WGS84_F * (2.0 - WGS84_F);
    let r = p[0].hypot(p[1]);
    if r.hypot(p[2]) < 1_000.0 {
        return None;
    }
    let longitude = p[1].atan2(p[0]);
    let mut latitude = p[2].atan2(r * (1.0 - e2));
    let mut height = 0.0;
    for _ in 0..8 {
        let sin_lat = latitude.sin();
        let n = WGS84_A / (1.0 - e2 * sin_lat * sin_lat).sqrt();
        height = if latitude.cos().abs() > 1e-9 {
            r / latitude.cos() - n
        } else {
            p[2].abs() - n * (1.0 - e2)
        };
        latitude = p[2].atan2(r * (1.0 - e2 * n / (n + height)));
    }
    Some(Geodetic {
        latitude,
        longitude,
        height,
    })
}

/// A local east-north-up frame at an Earth-centred origin, as CesiumJS's
/// `Transforms.eastNorthUpToFixedFrame` makes it: up is the ellipsoid's normal direction
/// at the origin (the gradient of the ellipsoid's equation there), east is perpendicular
/// to up and the Earth's axis, north completes the right-handed frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EastNorthUp {
    pub origin: [f64; 3],
    pub east: [f64; 3],
    pub north: [f64; 3],
    pub up: [f64; 3],
}

impl EastNorthUp {
    /// The frame at `origin`; `None` for an origin on the Earth's axis (no east there) or
    /// near its centre.
    pub fn at(origin: [f64; 3]) -> Option<Self> {
        if origin.iter().any(|v| !v.is_finite()) || origin[0].hypot(origin[1]) < 1e-3 {
            return None;
        }
        let a2 = WGS84_A * WGS84_A;
        let b2 = WGS84_B * WGS84_B;
        let up = normalise([origin[0] / a2, origin[1] / a2, origin[2] / b2])?;
        let east = normalise([-origin[1], origin[0], 0.0])?;
        let north = cross(up, east);
        Some(Self {
            origin,
            east,
            north,
            up,
        })
    }

    /// East, north and up coordinates of an Earth-centred point.
    pub fn local(&self, p: [f64; 3]) -> [f64; 3] {
        let d = [p[0] - self.origin[0], p[1] - self.origin[1], p[2] - self.origin[2]];
        [dot(self.east, d), dot(self.north, d), dot(self.up, d)]
    }

    /// East, north and up components of an Earth-centred direction.
    pub fn local_direction(&self, v: [f64; 3]) -> [f64; 3] {
        [dot(self.east, v), dot(self.north, v), dot(self.up, v)]
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalise(v: [f64; 3]) -> Option<[f64; 3]> {
    let len = dot(v, v).sqrt();
    (len > 0.0 && len.is_finite()).then(|| v.map(|x| x / len))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn berlin() -> Geodetic {
        Geodetic {
            latitude: 52.516_275_f64.to_radians(),
            longitude: 13.377_704_f64.to_radians(),
            height: 34.0,
        }
    }

    #[test]
    fn geodetic_round_trips_to_a_tenth_of_a_millimetre() {
        for (lat, lon, h) in [
            (52.516_275, 13.377_704, 34.0),
            (0.0, 0.0, 0.0),
            (-33.86, 151.21, 58.0),
            (89.9, -120.0, 2_000.0),
            (-89.99, 45.0, -100.0),
            (27.98, 86.92, 8_848.0),
        ] {
            let g = Geodetic {
                latitude: f64::to_radians(lat),
                longitude: f64::to_radians(lon),
                height: h,
            };
            let p = to_ecef(g);
            let back = to_geodetic(p).expect("near the surface");
            let again = to_ecef(back);
            let error = (0..3).map(|a| (again[a] - p[a]).powi(2)).sum::<f64>().sqrt();
            assert!(error < 1e-4, "({lat}, {lon}, {h}): {error} m");
            assert!((back.height - h).abs() < 1e-4, "({lat}, {lon}): height {}", back.height);
        }
    }

    #[test]
    fn the_frame_matches_the_textbook_rotation_on_the_ellipsoid() {
        // On the surface the ellipsoid's gradient is the geodetic normal.
        let g = Geodetic {
            height: 0.0,
            ..berlin()
        };
        let frame = EastNorthUp::at(to_ecef(g)).expect("frame");
        let (sl, cl) = g.latitude.sin_cos();
        let (so, co) = g.longitude.sin_cos();
        let expected = [[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]];
        for (axis, want) in [frame.east, frame.north, frame.up].iter().zip(expected) {
            for c in 0..3 {
                assert!((axis[c] - want[c]).abs() < 1e-12, "{axis:?} vs {want:?}");
            }
        }
        // A point 100 m up, 200 m east and 300 m north of the origin.
        let p: [f64; 3] = std::array::from_fn(|c| {
            frame.origin[c] + 200.0 * frame.east[c] + 300.0 * frame.north[c] + 100.0 * frame.up[c]
        });
        let local = frame.local(p);
        for (got, want) in local.iter().zip([200.0, 300.0, 100.0]) {
            assert!((got - want).abs() < 1e-6, "{local:?}");
        }
    }

    #[test]
    fn no_frame_on_the_axis_or_from_non_finite_coordinates() {
        assert!(EastNorthUp::at([0.0, 0.0, WGS84_B]).is_none());
        assert!(EastNorthUp::at([f64::NAN, 1.0, 2.0]).is_none());
        assert!(to_geodetic([f64::INFINITY, 0.0, 0.0]).is_none());
        assert!(to_geodetic([1.0, 2.0, 3.0]).is_none());
    }
}
