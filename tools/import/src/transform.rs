//! Column-major 4×4 transforms in f64, as glTF and 3D Tiles store them: node and tile
//! placement, and the normals they carry.

/// A column-major 4×4 matrix (`m[column][row]`), as glTF and 3D Tiles store them.
pub(crate) type Mat4 = [[f64; 4]; 4];

pub(crate) fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    // Column-major like glTF: m[column][row].
    let mut out = [[0.0; 4]; 4];
    for (c, column) in out.iter_mut().enumerate() {
        for (r, value) in column.iter_mut().enumerate() {
            *value = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    out
}

pub(crate) fn transform_point(m: &Mat4, p: [f32; 3]) -> [f64; 3] {
    let p = p.map(f64::from);
    [0, 1, 2].map(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

/// Inverse transpose of the upper 3×3 (for normals) and its determinant's sign.
pub(crate) fn normal_matrix(m: &Mat4) -> ([[f64; 3]; 3], f64) {
    let a = |r: usize, c: usize| m[c][r];
    let cof = |r0: usize, r1: usize, c0: usize, c1: usize| a(r0, c0) * a(r1, c1) - a(r0, c1) * a(r1, c0);
    // Cofactor matrix = det · inverse transpose; the scale does not matter for unit normals.
    let cofactor = [
        [cof(1, 2, 1, 2), -cof(1, 2, 0, 2), cof(1, 2, 0, 1)],
        [-cof(0, 2, 1, 2), cof(0, 2, 0, 2), -cof(0, 2, 0, 1)],
        [cof(0, 1, 1, 2), -cof(0, 1, 0, 2), cof(0, 1, 0, 1)],
    ];
    let det = a(0, 0) * cofactor[0][0] + a(0, 1) * cofactor[0][1] + a(0, 2) * cofactor[0][2];
    (cofactor, det)
}

pub(crate) fn transform_normal(n3: &[[f64; 3]; 3], det: f64, n: [f32; 3]) -> [f32; 3] {
    let n = n.map(f64::from);
    let sign = if det < 0.0 { -1.0 } else { 1.0 };
    let v = [0, 1, 2].map(|r| sign * (n3[r][0] * n[0] + n3[r][1] * n[1] + n3[r][2] * n[2]));
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        v.map(|x| (x / len) as f32)
    } else {
        [0.0, 1.0, 0.0]
    }
}

/// The identity transform.
pub(crate) const IDENTITY: Mat4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];
