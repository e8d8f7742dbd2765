//! Camera images rendered by casting one ray per pixel through the voxel world, and the
//! simulated LiDAR.
//!
//! Pixel convention (as `occ_geometry::camera`): the ray of pixel column `u`, row `v` goes
//! through the image point `(u, v)`, i.e. `u = fx·X/Z + cx` is the pixel centre.
//!
//! Appearance of a surface hit (all factors are luminance-only, so a pixel's chromaticity is
//! its class's, see [`super::classes`]): class base colour × voxel shade code (windows, tyres,
//! lane markings, car paint variants) × face lighting (sun from above and the front-left) ×
//! per-voxel and 5 cm texture noise × distance darkening (−30 % at 80 m) × per-pixel noise;
//! beyond 55 m a haze blends towards the horizon colour. Rays that leave the world or go past
//! `t_max` show a sky gradient with clouds (or hazy far ground below the horizon).

use super::classes::{BASE_COLOR, REFLECTIVITY, SIDEWALK, TERRAIN, VEGETATION};
use super::layout::SHADE_FACTOR;
use super::util::{hash3, unit, value_noise2};
use super::vis::Marker;
use super::world::{class_of, shade_of, voxel_box, Hit, World};
use occ_geometry::{transform_point, Mat4, PinholeCamera};
use rayon::prelude::*;

/// A camera placed in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct CamRig {
    pub cam: PinholeCamera,
    /// Rigid transform camera (OpenCV axes: x right, y down, z forward) -> world.
    pub world_from_cam: Mat4,
}

impl CamRig {
    /// World-frame unit direction of the ray through pixel `(u, v)` and the camera centre.
    pub(crate) fn ray(&self, u: f64, v: f64) -> ([f64; 3], [f64; 3]) {
        let dc = [
            (u - self.cam.cx) / self.cam.fx,
            (v - self.cam.cy) / self.cam.fy,
            1.0,
        ];
        let m = &self.world_from_cam;
        let mut d = [0.0; 3];
        for (r, dr) in d.iter_mut().enumerate() {
            *dr = m[r][0] * dc[0] + m[r][1] * dc[1] + m[r][2] * dc[2];
        }
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        (
            transform_point(m, [0.0, 0.0, 0.0]),
            [d[0] / n, d[1] / n, d[2] / n],
        )
    }
}

const HORIZON: [f32; 3] = [200.0, 214.0, 232.0];
const ZENITH: [f32; 3] = [88.0, 138.0, 212.0];

fn sky(seed: u64, d: [f64; 3]) -> [f32; 3] {
    if d[2] < 0.0 {
        let w = (-d[2] * 8.0).min(1.0) as f32;
        let ground = [128.0, 132.0, 126.0];
        return [0, 1, 2].map(|i| HORIZON[i] * (1.0 - w) + ground[i] * w);
    }
    let e = (d[2].min(1.0)).powf(0.6) as f32;
    let mut c = [0, 1, 2].map(|i| HORIZON[i] * (1.0 - e) + ZENITH[i] * e);
    let s = 1.0 / (d[2] + 0.08);
    let n = value_noise2(seed ^ 0xc10d, d[0] * s * 2.0, d[1] * s * 2.0) * 0.6
        + value_noise2(seed ^ 0xc10e, d[0] * s * 6.0, d[1] * s * 6.0) * 0.4;
    if n > 0.55 {
        let w = ((n - 0.55) * 3.0).min(0.85) as f32;
        c = [0, 1, 2].map(|i| c[i] * (1.0 - w) + 242.0 * w);
    }
    c
}

/// Colour of a surface hit (before quantisation).
fn shade_hit(
    world: &World,
    seed: u64,
    o: [f64; 3],
    d: [f64; 3],
    h: &Hit,
    pixel_noise: f32,
) -> [f32; 3] {
    let cls = class_of(h.vox) as usize;
    let base = BASE_COLOR.get(cls).copied().unwrap_or([255, 0, 255]);
    let g = [0, 1, 2].map(|a| world.off[a] + h.ijk[a] as i64);
    let p = [o[0] + h.t * d[0], o[1] + h.t * d[1], o[2] + h.t * d[2]];
    // face lighting: outward normal is -dir_sign along the entry axis
    let up = h.dir_sign < 0;
    let light: f32 = match (h.axis, up) {
        (2, true) => 1.0,
        (2, false) => 0.45,
        (0, true) => 0.78,
        (0, false) => 0.68,
        (1, true) => 0.86,
        _ => 0.6,
    };
    let (a1, a2) = match h.axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let amp: f32 = match cls as u8 {
        VEGETATION | TERRAIN => 0.3,
        1..=8 | 20..=24 => 0.06,
        _ => 0.14,
    };
    let fine = unit(hash3(
        seed ^ 0x7e57,
        (p[a1] / 0.05).floor() as i64,
        (p[a2] / 0.05).floor() as i64,
        (h.axis * 32 + cls) as i64,
    )) as f32;
    let vox_n = unit(hash3(seed ^ 0x0b0e, g[0], g[1], g[2])) as f32;
    let mut f = SHADE_FACTOR[shade_of(h.vox) as usize]
        * light
        * (1.0 - amp + 2.0 * amp * fine)
        * (0.92 + 0.16 * vox_n)
        * pixel_noise;
    if cls as u8 == SIDEWALK && h.axis == 2 {
        let tile = |v: f64| (v / 0.6).rem_euclid(1.0) < 0.07;
        if tile(p[0]) || tile(p[1]) {
            f *= 0.8;
        }
    }
    f *= 1.0 - 0.3 * (h.t / 80.0).min(1.0) as f32;
    let mut c = [0, 1, 2].map(|i| base[i] as f32 * f);
    let mx = c[0].max(c[1]).max(c[2]);
    if mx > 255.0 {
        let s = 255.0 / mx;
        c = c.map(|v| v * s);
    }
    if h.t > 55.0 {
        let w = (((h.t - 55.0) / 200.0).min(0.5)) as f32;
        c = [0, 1, 2].map(|i| c[i] * (1.0 - w) + HORIZON[i] * w);
    }
    c
}

/// Render one camera into RGB8 (row-major). `marker` receives every voxel the pixel rays
/// traverse or stop in. `tex_seed` fixes the surface textures and clouds (the same for every
/// frame of a sequence), `frame_seed` the per-pixel noise.
pub(crate) fn render(
    world: &World,
    rig: &CamRig,
    t_max: f64,
    tex_seed: u64,
    frame_seed: u64,
    marker: Option<Marker<'_>>,
) -> Vec<u8> {
    let (w, h) = (rig.cam.width, rig.cam.height);
    let visit = marker.map_or(([0; 3], [0; 3]), |m| m.local_box(world.off));
    let mark = |l: [usize; 3]| {
        if let Some(m) = marker {
            m.mark([
                world.off[0] + l[0] as i64,
                world.off[1] + l[1] as i64,
                world.off[2] + l[2] as i64,
            ]);
        }
    };
    let rows: Vec<Vec<u8>> = (0..h)
        .into_par_iter()
        .map(|v| {
            let mut rgb = Vec::with_capacity(3 * w);
            for u in 0..w {
                let (o, d) = rig.ray(u as f64, v as f64);
                let hit = world.trace(o, d, t_max, &visit, mark);
                let pn =
                    0.97 + 0.06 * unit(hash3(frame_seed ^ 0x9e11, u as i64, v as i64, 0)) as f32;
                let c = match &hit {
                    Some(hh) => {
                        mark(hh.ijk);
                        shade_hit(world, tex_seed, o, d, hh, pn)
                    }
                    None => sky(tex_seed, d).map(|x| x * pn),
                };
                rgb.extend(c.map(|x| x.round().clamp(0.0, 255.0) as u8));
            }
            rgb
        })
        .collect();
    rows.concat()
}

/// A spinning multi-beam LiDAR.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LidarSpec {
    /// Number of beams (rows).
    pub beams: usize,
    /// Elevation of the top and bottom beams (degrees; beams are evenly spaced between).
    pub elev_top_deg: f64,
    pub elev_bottom_deg: f64,
    /// Azimuth steps per revolution.
    pub columns: usize,
    /// Maximum range (m).
    pub max_range_m: f64,
}

/// A LiDAR return: `(x, y, z, intensity)`, scene class, global voxel, beam index.
type ScanPoint = ([f32; 4], u8, [i64; 3], u8);

/// One simulated scan.
pub(crate) struct Scan {
    /// `(x, y, z, intensity)` in the sensor frame (axes parallel to the world's).
    pub points: Vec<[f32; 4]>,
    /// Scene class of each point.
    pub classes: Vec<u8>,
    /// Global voxel of each point.
    pub voxels: Vec<[i64; 3]>,
    /// Beam index (0 = top) of each point.
    pub rings: Vec<u8>,
}

/// Cast every beam of `spec` from `origin` (world metres; sensor axes = world axes). Points are
/// the ray's entry point into the hit voxel, moved at most 1 mm so that they lie strictly inside
/// that voxel (so voxelising the scan gives back exactly the hit voxels). Columns are ordered by
/// azimuth from −180°, beams from top to bottom within a column.
pub(crate) fn scan(
    world: &World,
    spec: &LidarSpec,
    origin: [f64; 3],
    marker: Option<Marker<'_>>,
) -> Scan {
    let visit = marker.map_or(([0; 3], [0; 3]), |m| m.local_box(world.off));
    let cols: Vec<Vec<ScanPoint>> = (0..spec.columns)
        .into_par_iter()
        .map(|c| {
            let az = -std::f64::consts::PI
                + 2.0 * std::f64::consts::PI * (c as f64 + 0.5) / spec.columns as f64;
            let mut out = Vec::with_capacity(spec.beams);
            for b in 0..spec.beams {
                let el_deg = if spec.beams > 1 {
                    spec.elev_top_deg
                        + (spec.elev_bottom_deg - spec.elev_top_deg) * b as f64
                            / (spec.beams - 1) as f64
                } else {
                    spec.elev_top_deg
                };
                let el = el_deg.to_radians();
                let d = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
                let hit = world.trace(origin, d, spec.max_range_m, &visit, |l| {
                    if let Some(m) = marker {
                        m.mark([
                            world.off[0] + l[0] as i64,
                            world.off[1] + l[1] as i64,
                            world.off[2] + l[2] as i64,
                        ]);
                    }
                });
                if let Some(h) = hit {
                    let g = [0, 1, 2].map(|a| world.off[a] + h.ijk[a] as i64);
                    if let Some(m) = marker {
                        m.mark(g);
                    }
                    let (lo, hi) = voxel_box(world, h.ijk);
                    let p = [0, 1, 2]
                        .map(|a| (origin[a] + h.t * d[a]).clamp(lo[a] + 1e-3, hi[a] - 1e-3));
                    let cos_inc = d[h.axis].abs() as f32;
                    let cls = class_of(h.vox);
                    let refl = REFLECTIVITY.get(cls as usize).copied().unwrap_or(0.3);
                    let intensity = (refl * (0.55 + 0.45 * cos_inc)).clamp(0.0, 1.0);
                    let rel = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
                    out.push((
                        [rel[0] as f32, rel[1] as f32, rel[2] as f32, intensity],
                        cls,
                        g,
                        b.min(255) as u8,
                    ));
                }
            }
            out
        })
        .collect();
    let n: usize = cols.iter().map(Vec::len).sum();
    let mut s = Scan {
        points: Vec::with_capacity(n),
        classes: Vec::with_capacity(n),
        voxels: Vec::with_capacity(n),
        rings: Vec::with_capacity(n),
    };
    for col in cols {
        for (p, c, g, r) in col {
            s.points.push(p);
            s.classes.push(c);
            s.voxels.push(g);
            s.rings.push(r);
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::layout::{Pattern, Prim, Shape};
    use crate::synthetic::world::Lattice;

    fn wall_world() -> World {
        let lat = Lattice {
            origin_m: [0.0, -10.0, -2.0],
            voxel_size_m: 0.2,
        };
        let mut w = World::new(lat, [0, 0, 0], [100, 100, 40], 3);
        // ground plane (road) and a wall (building) at x in [10, 10.4]
        w.rasterize(&Prim {
            shape: Shape::Box {
                c: [10.0, 0.0, -1.9],
                h: [10.0, 10.0, 0.1],
                yaw: 0.0,
            },
            class: 9,
            shade: 0,
            pattern: Pattern::Solid,
        });
        w.rasterize(&Prim {
            shape: Shape::Box {
                c: [10.2, 0.0, 1.0],
                h: [0.2, 10.0, 3.0],
                yaw: 0.0,
            },
            class: 13,
            shade: 0,
            pattern: Pattern::Solid,
        });
        w
    }

    #[test]
    fn lidar_points_lie_in_their_voxels_and_at_the_right_range() {
        let w = wall_world();
        let spec = LidarSpec {
            beams: 16,
            elev_top_deg: 2.0,
            elev_bottom_deg: -24.8,
            columns: 90,
            max_range_m: 80.0,
        };
        let origin = [2.0, 0.1, 0.0];
        let s = scan(&w, &spec, origin, None);
        assert!(s.points.len() > 100);
        let lat = w.lattice;
        for (p, g) in s.points.iter().zip(&s.voxels) {
            let pw = [
                p[0] as f64 + origin[0],
                p[1] as f64 + origin[1],
                p[2] as f64 + origin[2],
            ];
            assert_eq!(lat.index_of(pw), *g);
        }
        // the beam straight ahead at elevation 0..2 deg hits the wall face at x = 10.0
        let ahead: Vec<_> = s
            .points
            .iter()
            .zip(&s.classes)
            .filter(|(p, c)| **c == 13 && p[1].abs() < 0.5 && p[2].abs() < 0.3)
            .collect();
        assert!(!ahead.is_empty());
        for (p, _) in ahead {
            assert!((p[0] as f64 - 8.0).abs() < 0.01, "{p:?}");
        }
    }

    #[test]
    fn render_shows_class_colours_and_sky() {
        let w = wall_world();
        let cam = PinholeCamera {
            fx: 50.0,
            fy: 50.0,
            cx: 40.0,
            cy: 20.0,
            width: 80,
            height: 40,
        };
        // camera looking along +x: cam z = world x, cam x = -world y, cam y = -world z
        let world_from_cam = [
            [0.0, 0.0, 1.0, 2.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let rig = CamRig {
            cam,
            world_from_cam,
        };
        let rgb = render(&w, &rig, 100.0, 1, 2, None);
        let all: Vec<u8> = (1..25).collect();
        let none = ([0; 3], [0; 3]);
        let mut n_ok = 0;
        let mut n = 0;
        let mut hits = Vec::new();
        for v in 0..40 {
            for u in 0..80 {
                let (o, d) = rig.ray(u as f64, v as f64);
                let hit = w.trace(o, d, 100.0, &none, |_| {});
                hits.push(hit.map(|h| h.ijk));
                if let Some(hh) = hit {
                    let i = v * 80 + u;
                    let px = [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]];
                    n += 1;
                    n_ok += usize::from(
                        crate::synthetic::classes::nearest_class_by_chroma(px, &all)
                            == Some(class_of(hh.vox)),
                    );
                } else {
                    // sky: bluish-white, brighter in blue than red
                    let i = v * 80 + u;
                    assert!(rgb[3 * i + 2] > rgb[3 * i]);
                }
            }
        }
        assert!(n > 1000);
        assert_eq!(n_ok, n, "every hit pixel has its class chromaticity");
        // the centre pixel sees the wall
        let c = hits[20 * 80 + 40].unwrap();
        assert_eq!(class_of(w.vox[w.index(c)]), 13);
    }
}
