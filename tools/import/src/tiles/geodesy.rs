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

/// A local east-north-up frame at an Earth-centred origin: the topocentric frame of the
/// CRS the import writes (EPSG method 9837). Up is the ellipsoid's normal through the
/// origin, from its geodetic latitude and longitude; east is perpendicular to up and the
/// Earth's axis, north completes the right-handed frame. CesiumJS's
/// `Transforms.eastNorthUpToFixedFrame` takes up as the gradient of the ellipsoid's
/// equation at the origin instead, which is the same on the surface but turns by about
/// `h / a · e² · sin 2φ / 2` at a height `h` above it: 4 µrad at 8,848 m, a millimetre
/// 250 m from the origin, so a frame declared topocentric would not be.
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
        let Geodetic {
            latitude, longitude, ..
        } = to_geodetic(origin)?;
        let (sin_lat, cos_lat) = latitude.sin_cos();
        let (sin_lon, cos_lon) = longitude.sin_cos();
        let up = [cos_lat * cos_lon, cos_lat * sin_lon, sin_lat];
        let east = [-sin_lon, cos_lon, 0.0];
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

/// A transverse Mercator projection of the WGS 84 ellipsoid (Krüger's series to sixth
/// order in the third flattening, as Karney 2011 gives it: well below a millimetre within
/// a UTM zone).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransverseMercator {
    /// Central meridian, radians.
    pub central_meridian: f64,
    pub scale: f64,
    pub false_easting: f64,
    pub false_northing: f64,
}

impl TransverseMercator {
    /// UTM zone `zone` (1 to 60), northern or southern hemisphere.
    pub fn utm(zone: u32, north: bool) -> Self {
        Self {
            central_meridian: (f64::from(zone) * 6.0 - 183.0).to_radians(),
            scale: 0.9996,
            false_easting: 500_000.0,
            false_northing: if north { 0.0 } else { 10_000_000.0 },
        }
    }

    /// Easting and northing of geodetic latitude and longitude (radians).
    pub fn project(&self, latitude: f64, longitude: f64) -> [f64; 2] {
        let n = WGS84_F / (2.0 - WGS84_F);
        let (n2, n3) = (n * n, n * n * n);
        let (n4, n5, n6) = (n2 * n2, n2 * n3, n3 * n3);
        let a = WGS84_A / (1.0 + n) * (1.0 + n2 / 4.0 + n4 / 64.0 + n6 / 256.0);
        let alpha = [
            n / 2.0 - 2.0 * n2 / 3.0 + 5.0 * n3 / 16.0 + 41.0 * n4 / 180.0 - 127.0 * n5 / 288.0 + 7891.0 * n6 / 37800.0,
            13.0 * n2 / 48.0 - 3.0 * n3 / 5.0 + 557.0 * n4 / 1440.0 + 281.0 * n5 / 630.0
                - 1_983_433.0 * n6 / 1_935_360.0,
            61.0 * n3 / 240.0 - 103.0 * n4 / 140.0 + 15061.0 * n5 / 26880.0 + 167_603.0 * n6 / 181_440.0,
            49561.0 * n4 / 161_280.0 - 179.0 * n5 / 168.0 + 6_601_661.0 * n6 / 7_257_600.0,
            34729.0 * n5 / 80640.0 - 3_418_889.0 * n6 / 1_995_840.0,
            212_378_941.0 * n6 / 319_334_400.0,
        ];
        let e = 2.0 * n.sqrt() / (1.0 + n);
        let sin_lat = latitude.sin();
        let t = (sin_lat.atanh() - e * (e * sin_lat).atanh()).sinh();
        let dl = longitude - self.central_meridian;
        let xi0 = t.atan2(dl.cos());
        let eta0 = (dl.sin() / (1.0 + t * t).sqrt()).atanh();
        let (mut xi, mut eta) = (xi0, eta0);
        for (j, a_j) in alpha.iter().enumerate() {
            let k = 2.0 * (j as f64 + 1.0);
            xi += a_j * (k * xi0).sin() * (k * eta0).cosh();
            eta += a_j * (k * xi0).cos() * (k * eta0).sinh();
        }
        [
            self.false_easting + self.scale * a * eta,
            self.false_northing + self.scale * a * xi,
        ]
    }
}

/// The UTM projection an EPSG code names, with its datum's name: WGS 84 / UTM (32601–32660
/// north, 32701–32760 south) and ETRS89 / UTM (25828–25838, zones 28–38 north).
pub fn utm_of_epsg(code: u32) -> Option<(TransverseMercator, &'static str)> {
    match code {
        32601..=32660 => Some((TransverseMercator::utm(code - 32600, true), "WGS 84")),
        32701..=32760 => Some((TransverseMercator::utm(code - 32700, false), "WGS 84")),
        25828..=25838 => Some((TransverseMercator::utm(code - 25800, true), "ETRS89")),
        _ => None,
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
    fn the_frame_matches_the_textbook_rotation_on_and_off_the_ellipsoid() {
        // The topocentric rotation at the origin's geodetic latitude and longitude, on the
        // surface and 8,848 m above or 430 m below it (where the ellipsoid's gradient at the
        // origin turns by up to 4 µrad from the normal).
        for height in [0.0, 8_848.0, -430.0] {
            let g = Geodetic { height, ..berlin() };
            let frame = EastNorthUp::at(to_ecef(g)).expect("frame");
            let (sl, cl) = g.latitude.sin_cos();
            let (so, co) = g.longitude.sin_cos();
            let expected = [[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]];
            for (axis, want) in [frame.east, frame.north, frame.up].iter().zip(expected) {
                for c in 0..3 {
                    assert!((axis[c] - want[c]).abs() < 1e-12, "{height} m: {axis:?} vs {want:?}");
                }
            }
        }
        let g = Geodetic {
            height: 0.0,
            ..berlin()
        };
        let frame = EastNorthUp::at(to_ecef(g)).expect("frame");
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
    fn utm_matches_proj_to_a_millimetre() {
        // Reference values from PROJ 9.5.1 (pyproj 3.7.2, EPSG:4326 to EPSG:32633/32756).
        for (code, lat, lon, easting, northing) in [
            (32633, 52.516_275, 13.377_704, 389_918.041_6, 5_819_699.132_4),
            (32633, 52.52, 13.405, 391_779.259_3, 5_820_072.159_2),
            (32633, 48.0, 9.0, 52_512.810_2, 5_333_742.748_0),
            (32633, 60.0, 18.0, 667_294.821_1, 6_655_205.483_6),
            (32633, 52.516_275, 15.0, 500_000.0, 5_818_462.315_0),
            (32756, -33.86, 151.21, 334_416.394_0, 6_251_925.360_4),
        ] {
            let (tm, _) = utm_of_epsg(code).expect("UTM");
            let [e, n] = tm.project(f64::to_radians(lat), f64::to_radians(lon));
            assert!(
                (e - easting).abs() < 1e-3 && (n - northing).abs() < 1e-3,
                "({lat}, {lon}): {e}, {n}"
            );
        }
        assert!(utm_of_epsg(4326).is_none() && utm_of_epsg(32661).is_none());
    }

    #[test]
    fn no_frame_on_the_axis_or_from_non_finite_coordinates() {
        assert!(EastNorthUp::at([0.0, 0.0, WGS84_B]).is_none());
        assert!(EastNorthUp::at([f64::NAN, 1.0, 2.0]).is_none());
        assert!(to_geodetic([f64::INFINITY, 0.0, 0.0]).is_none());
        assert!(to_geodetic([1.0, 2.0, 3.0]).is_none());
    }
}
