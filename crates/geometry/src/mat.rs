//! Small dense matrix helpers for rigid/projective transforms (row-major `[[f64; 4]; 4]`).
//!
//! Transforms are named `b_from_a`: `p_b = b_from_a · p_a`, so `c_from_a = mat4_mul(&c_from_b, &b_from_a)`.

/// Row-major 4x4 matrix acting on column vectors `[x, y, z, 1]`.
pub type Mat4 = [[f64; 4]; 4];

/// Row-major 3x3 matrix (used for camera intrinsics and 2D image affines in homogeneous form).
pub type Mat3 = [[f64; 3]; 3];

/// The 4x4 identity.
pub fn mat4_identity() -> Mat4 {
    let mut m = [[0.0; 4]; 4];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m
}

/// Matrix product `a · b` (apply `b` first, then `a`).
pub fn mat4_mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut out = [[0.0; 4]; 4];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

/// General 4x4 inverse by Gauss-Jordan elimination with partial pivoting.
/// Returns `None` when the matrix is singular (a pivot below `1e-12` times the largest entry)
/// or contains non-finite values.
pub fn mat4_inverse(m: &Mat4) -> Option<Mat4> {
    let scale = m
        .iter()
        .flat_map(|r| r.iter())
        .fold(0.0f64, |acc, v| acc.max(v.abs()));
    if !scale.is_finite() || scale == 0.0 {
        return None;
    }
    let mut a = *m;
    let mut inv = mat4_identity();
    for col in 0..4 {
        let pivot_row =
            (col..4).max_by(|&r1, &r2| a[r1][col].abs().total_cmp(&a[r2][col].abs()))?;
        if a[pivot_row][col].abs() <= 1e-12 * scale {
            return None;
        }
        a.swap(col, pivot_row);
        inv.swap(col, pivot_row);
        let p = a[col][col];
        for j in 0..4 {
            a[col][j] /= p;
            inv[col][j] /= p;
        }
        for r in 0..4 {
            if r != col {
                let f = a[r][col];
                if f != 0.0 {
                    for j in 0..4 {
                        a[r][j] -= f * a[col][j];
                        inv[r][j] -= f * inv[col][j];
                    }
                }
            }
        }
    }
    Some(inv)
}

/// Apply the affine part of `m` to `p` (homogeneous w = 1, no perspective division):
/// returns the first three rows of `m · [p, 1]`.
pub fn transform_point(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    let mut out = [0.0; 3];
    for (i, o) in out.iter_mut().enumerate() {
        *o = m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3];
    }
    out
}

/// The 3x3 identity.
pub fn mat3_identity() -> Mat3 {
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
}

/// Matrix product `a · b` for 3x3 matrices.
pub fn mat3_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

/// Determinant of a 3x3 matrix (cofactor expansion along the first row).
pub fn mat3_det(m: &Mat3) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// 3x3 inverse via the adjugate; `None` if singular (|det| <= 1e-12 · max|entry|³) or non-finite.
pub fn mat3_inverse(m: &Mat3) -> Option<Mat3> {
    let det = mat3_det(m);
    let scale = m
        .iter()
        .flat_map(|r| r.iter())
        .fold(0.0f64, |acc, v| acc.max(v.abs()));
    if !det.is_finite() || !scale.is_finite() || det.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [c(1, 2, 1, 2), -c(0, 2, 1, 2), c(0, 1, 1, 2)],
        [-c(1, 2, 0, 2), c(0, 2, 0, 2), -c(0, 1, 0, 2)],
        [c(1, 2, 0, 1), -c(0, 2, 0, 1), c(0, 1, 0, 1)],
    ];
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = adj[i][j] / det;
        }
    }
    Some(out)
}

/// Rigid transform from a unit quaternion `(w, x, y, z)` (the nuScenes convention) and a translation.
/// The quaternion is normalised first; a zero quaternion gives `None`.
pub fn mat4_from_quat_translation(q_wxyz: [f64; 4], t: [f64; 3]) -> Option<Mat4> {
    let n = q_wxyz.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !n.is_finite() || n < 1e-12 || t.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let [w, x, y, z] = [q_wxyz[0] / n, q_wxyz[1] / n, q_wxyz[2] / n, q_wxyz[3] / n];
    Some([
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
            t[0],
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
            t[1],
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
            t[2],
        ],
        [0.0, 0.0, 0.0, 1.0],
    ])
}

/// Unit quaternion `(w, x, y, z)` with `w >= 0` of the rotation part of `m` (assumed orthonormal).
pub fn quat_from_mat4(m: &Mat4) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
        ]
    };
    if q[0] < 0.0 {
        [-q[0], -q[1], -q[2], -q[3]]
    } else {
        q
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // matrix entries are naturally indexed by (i, j)
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_rigid(rng: &mut ChaCha8Rng) -> Mat4 {
        let q = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let t = [
            rng.random_range(-5.0..5.0),
            rng.random_range(-5.0..5.0),
            rng.random_range(-5.0..5.0),
        ];
        mat4_from_quat_translation(q, t).unwrap()
    }

    #[test]
    fn inverse_times_matrix_is_identity() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..100 {
            let mut m = [[0.0; 4]; 4];
            for r in m.iter_mut() {
                for v in r.iter_mut() {
                    *v = rng.random_range(-3.0..3.0);
                }
            }
            let inv = mat4_inverse(&m).unwrap();
            let p = mat4_mul(&m, &inv);
            for i in 0..4 {
                for j in 0..4 {
                    let e = if i == j { 1.0 } else { 0.0 };
                    assert!((p[i][j] - e).abs() < 1e-9, "{p:?}");
                }
            }
        }
        let singular = [
            [1.0, 2.0, 3.0, 4.0],
            [2.0, 4.0, 6.0, 8.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        assert!(mat4_inverse(&singular).is_none());
        assert!(mat4_inverse(&[[f64::NAN; 4]; 4]).is_none());
    }

    #[test]
    fn mat3_inverse_matches() {
        let k = [
            [718.856, 0.0, 607.1928],
            [0.0, 718.856, 185.2157],
            [0.0, 0.0, 1.0],
        ];
        let inv = mat3_inverse(&k).unwrap();
        let p = mat3_mul(&k, &inv);
        for i in 0..3 {
            for j in 0..3 {
                assert!((p[i][j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert!(mat3_inverse(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [1.0, 0.0, 0.0]]).is_none());
    }

    #[test]
    fn quaternion_round_trip_and_known_rotation() {
        // 90 degrees about z: x axis -> y axis.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = mat4_from_quat_translation([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]).unwrap();
        let p = transform_point(&m, [1.0, 0.0, 0.0]);
        assert!(
            (p[0] - 1.0).abs() < 1e-12 && (p[1] - 3.0).abs() < 1e-12 && (p[2] - 3.0).abs() < 1e-12
        );
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for _ in 0..50 {
            let m = random_rigid(&mut rng);
            let q = quat_from_mat4(&m);
            let m2 = mat4_from_quat_translation(q, [m[0][3], m[1][3], m[2][3]]).unwrap();
            for i in 0..4 {
                for j in 0..4 {
                    assert!((m[i][j] - m2[i][j]).abs() < 1e-9);
                }
            }
        }
        assert!(mat4_from_quat_translation([0.0; 4], [0.0; 3]).is_none());
    }
}
