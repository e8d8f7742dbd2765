//! The voxelised world: a window of a global voxel lattice holding one byte per voxel
//! (scene class in the low 5 bits, shade code in the high 3 bits), rasterised from a
//! [`Layout`], and the ray caster (Amanatides–Woo DDA) used by the LiDAR and the cameras.

use super::layout::{Layout, Pattern, Prim, SH_DARK, SH_WHITE};
use super::util::{hash3, unit};

/// The global lattice: voxel `g = (i, j, k)` (signed) covers `origin + g·s .. origin + (g+1)·s`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Lattice {
    pub origin_m: [f64; 3],
    pub voxel_size_m: f64,
}

impl Lattice {
    /// Global index of the voxel containing `p`.
    #[cfg(test)]
    pub(crate) fn index_of(&self, p: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.origin_m[a]) / self.voxel_size_m).floor() as i64)
    }
    /// Centre of global voxel `g`.
    #[cfg(test)]
    pub(crate) fn center(&self, g: [i64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| self.origin_m[a] + (g[a] as f64 + 0.5) * self.voxel_size_m)
    }
}

/// A box of the global lattice with one byte per voxel.
#[derive(Clone, Debug)]
pub(crate) struct World {
    pub lattice: Lattice,
    /// Global index of local voxel (0, 0, 0).
    pub off: [i64; 3],
    pub dims: [usize; 3],
    /// Number of 4×4×4 bricks along each axis.
    bdims: [usize; 3],
    /// `class | shade << 5`, stored in 4×4×4 bricks of 64 bytes (one cache line; bricks and the
    /// voxels inside a brick in C order), so that rays in every direction read memory locally.
    /// Use [`World::index`].
    pub vox: Vec<u8>,
    /// One byte per brick: non-zero if the brick holds an occupied voxel (kept in cache by the
    /// ray caster so that empty space costs no access to `vox`); set by every write.
    bocc: Vec<u8>,
    /// Seed of the porous-vegetation hash.
    pub seed: u64,
}

/// Scene class stored in a voxel byte.
#[inline]
pub(crate) fn class_of(v: u8) -> u8 {
    v & 31
}

/// Shade code stored in a voxel byte.
#[inline]
pub(crate) fn shade_of(v: u8) -> u8 {
    v >> 5
}

/// First occupied voxel along a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Hit {
    /// Distance along the (unit) ray to the entry point of the voxel.
    pub t: f64,
    /// Local index of the voxel in the world window.
    pub ijk: [usize; 3],
    /// Axis of the face through which the ray entered (0, 1, 2), and the sign of the ray
    /// direction along it (the outward normal is `-sign` on that axis).
    pub axis: usize,
    pub dir_sign: i8,
    /// Voxel byte.
    pub vox: u8,
}

impl World {
    /// An empty window of `dims` voxels starting at global index `off`.
    pub(crate) fn new(lattice: Lattice, off: [i64; 3], dims: [usize; 3], seed: u64) -> Self {
        let bdims = dims.map(|d| d.div_ceil(4));
        let nb = bdims[0] * bdims[1] * bdims[2];
        World {
            lattice,
            off,
            dims,
            bdims,
            vox: vec![0; nb * 64],
            bocc: vec![0; nb],
            seed,
        }
    }

    /// Metric position of the window's minimum corner.
    pub(crate) fn min_m(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| self.lattice.origin_m[a] + self.off[a] as f64 * self.lattice.voxel_size_m)
    }

    /// Metric position of the window's maximum corner.
    pub(crate) fn max_m(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| {
            self.lattice.origin_m[a]
                + (self.off[a] + self.dims[a] as i64) as f64 * self.lattice.voxel_size_m
        })
    }

    /// Position of local voxel `ijk` in [`World::vox`].
    #[inline]
    pub(crate) fn index(&self, ijk: [usize; 3]) -> usize {
        let b = ((ijk[0] >> 2) * self.bdims[1] + (ijk[1] >> 2)) * self.bdims[2] + (ijk[2] >> 2);
        (b << 6) | ((ijk[0] & 3) << 4) | ((ijk[1] & 3) << 2) | (ijk[2] & 3)
    }

    /// Voxel byte at a global index, 0 outside the window.
    pub(crate) fn get_global(&self, g: [i64; 3]) -> u8 {
        let l = [0, 1, 2].map(|a| g[a] - self.off[a]);
        if (0..3).any(|a| l[a] < 0 || l[a] >= self.dims[a] as i64) {
            return 0;
        }
        self.vox[self.index([l[0] as usize, l[1] as usize, l[2] as usize])]
    }

    /// Local index range `[lo, hi)` of voxels whose centres may lie in `[min, max]`.
    fn range(&self, min: [f64; 3], max: [f64; 3]) -> Option<([usize; 3], [usize; 3])> {
        let w0 = self.min_m();
        let s = self.lattice.voxel_size_m;
        let mut lo = [0usize; 3];
        let mut hi = [0usize; 3];
        for a in 0..3 {
            let l = ((min[a] - w0[a]) / s - 0.5).ceil().max(0.0);
            let h = (((max[a] - w0[a]) / s - 0.5).floor() + 1.0).min(self.dims[a] as f64);
            if l.partial_cmp(&h) != Some(std::cmp::Ordering::Less) {
                return None;
            }
            lo[a] = l as usize;
            hi[a] = h as usize;
        }
        Some((lo, hi))
    }

    fn local_of_point(&self, p: [f64; 3]) -> Option<[usize; 3]> {
        let w0 = self.min_m();
        let s = self.lattice.voxel_size_m;
        let mut l = [0usize; 3];
        for a in 0..3 {
            let f = ((p[a] - w0[a]) / s).floor();
            if !(f >= 0.0 && f < self.dims[a] as f64) {
                return None;
            }
            l[a] = f as usize;
        }
        Some(l)
    }

    fn shade_at(&self, prim: &Prim, p: [f64; 3], g: [i64; 3]) -> Option<u8> {
        match prim.pattern {
            Pattern::Solid => Some(prim.shade),
            Pattern::Porous { keep } => {
                (unit(hash3(self.seed, g[0], g[1], g[2])) < keep).then_some(prim.shade)
            }
            Pattern::Stripes { period } => {
                let (lo, _) = prim.shape.aabb();
                Some(if ((p[2] - lo[2]) / period).floor() as i64 % 2 == 1 {
                    SH_WHITE
                } else {
                    prim.shade
                })
            }
            Pattern::Facade {
                floor_h,
                period,
                win_w,
                phase,
            } => {
                let (lo, _) = prim.shape.aabb();
                let zz = p[2] - lo[2];
                let in_floor = zz.rem_euclid(floor_h);
                let along = (p[0] + p[1] + phase).rem_euclid(period);
                let window =
                    zz > 0.6 && in_floor > 0.9 && in_floor < floor_h - 0.6 && along < win_w;
                Some(if window { SH_DARK } else { prim.shade })
            }
        }
    }

    /// Rasterise one primitive: every voxel whose centre lies inside, plus the voxels of its
    /// skeleton when the primitive is thinner than two voxels.
    pub(crate) fn rasterize(&mut self, prim: &Prim) {
        let (lo_m, hi_m) = prim.shape.aabb();
        let s = self.lattice.voxel_size_m;
        if let Some((lo, hi)) = self.range(lo_m, hi_m) {
            let w0 = self.min_m();
            for i in lo[0]..hi[0] {
                for j in lo[1]..hi[1] {
                    for k in lo[2]..hi[2] {
                        let p = [
                            w0[0] + (i as f64 + 0.5) * s,
                            w0[1] + (j as f64 + 0.5) * s,
                            w0[2] + (k as f64 + 0.5) * s,
                        ];
                        if prim.shape.contains(p) {
                            let g = [
                                self.off[0] + i as i64,
                                self.off[1] + j as i64,
                                self.off[2] + k as i64,
                            ];
                            if let Some(sh) = self.shade_at(prim, p, g) {
                                let idx = self.index([i, j, k]);
                                self.vox[idx] = prim.class | (sh << 5);
                                self.bocc[idx >> 6] = 1;
                            }
                        }
                    }
                }
            }
        }
        if prim.shape.min_extent() < 2.0 * s && !matches!(prim.pattern, Pattern::Porous { .. }) {
            for p in prim.shape.skeleton(0.5 * s) {
                if let Some(l) = self.local_of_point(p) {
                    let g = [0, 1, 2].map(|a| self.off[a] + l[a] as i64);
                    if let Some(sh) = self.shade_at(prim, p, g) {
                        let idx = self.index(l);
                        self.vox[idx] = prim.class | (sh << 5);
                        self.bocc[idx >> 6] = 1;
                    }
                }
            }
        }
    }

    /// Rasterise the ground plan and then every object whose bounding box meets the window.
    pub(crate) fn build(&mut self, layout: &Layout) {
        let s = self.lattice.voxel_size_m;
        let w0 = self.min_m();
        let mark_half_w = (0.5 * s).max(0.075);
        let dz = self.dims[2];
        for i in 0..self.dims[0] {
            for j in 0..self.dims[1] {
                let (x, y) = (w0[0] + (i as f64 + 0.5) * s, w0[1] + (j as f64 + 0.5) * s);
                let (cls, top, sh) = layout.plan.ground(x, y, mark_half_w);
                for k in 0..dz {
                    let z = w0[2] + (k as f64 + 0.5) * s;
                    if z >= top {
                        break;
                    }
                    // paint only the surface voxel
                    let top_voxel = z + s >= top;
                    let idx = self.index([i, j, k]);
                    self.vox[idx] = cls | (if top_voxel { sh } else { 0 } << 5);
                    self.bocc[idx >> 6] = 1;
                }
            }
        }
        let (wmin, wmax) = (self.min_m(), self.max_m());
        for o in &layout.objects {
            let (lo, hi) = o.aabb();
            if (0..3).all(|a| lo[a] <= wmax[a] && hi[a] >= wmin[a]) {
                for p in &o.prims {
                    self.rasterize(p);
                }
            }
        }
    }

    /// Cast a ray from `o` along the unit direction `d` up to distance `t_max`. Calls
    /// `on_free(local ijk)` for every empty voxel traversed before the hit inside `visit` (a
    /// local index box `[lo, hi)`); outside it, empty 4×4×4 bricks are skipped and their voxels
    /// may go unreported. Returns the first occupied voxel, if any. A ray starting outside the
    /// window enters it first; a ray starting inside an occupied voxel hits it at `t = 0`.
    pub(crate) fn trace<F: FnMut([usize; 3])>(
        &self,
        o: [f64; 3],
        d: [f64; 3],
        t_max: f64,
        visit: &([i64; 3], [i64; 3]),
        mut on_free: F,
    ) -> Option<Hit> {
        // bricks that intersect the visit box are traversed voxel by voxel
        let vb_lo = visit.0.map(|v| v.div_euclid(4));
        let vb_hi = visit.1.map(|v| (v + 3).div_euclid(4));
        let visit_empty = (0..3).any(|a| visit.0[a] >= visit.1[a]);
        let s = self.lattice.voxel_size_m;
        let w0 = self.min_m();
        let w1 = self.max_m();
        // slab intersection with the window box
        let mut t0 = 0.0f64;
        let mut t1 = t_max;
        let mut entry_axis = 0usize;
        for a in 0..3 {
            if d[a].abs() < 1e-12 {
                if o[a] < w0[a] || o[a] >= w1[a] {
                    return None;
                }
            } else {
                let inv = 1.0 / d[a];
                let (mut ta, mut tb) = ((w0[a] - o[a]) * inv, (w1[a] - o[a]) * inv);
                if ta > tb {
                    std::mem::swap(&mut ta, &mut tb);
                }
                if ta > t0 {
                    t0 = ta;
                    entry_axis = a;
                }
                t1 = t1.min(tb);
            }
        }
        if t0 > t1 {
            return None;
        }
        let p0 = [0, 1, 2].map(|a| o[a] + t0 * d[a]);
        let mut ijk = [0i64; 3];
        let mut step = [0i64; 3];
        let mut t_next = [f64::INFINITY; 3];
        let mut t_delta = [f64::INFINITY; 3];
        for a in 0..3 {
            let f = ((p0[a] - w0[a]) / s).floor() as i64;
            ijk[a] = f.clamp(0, self.dims[a] as i64 - 1);
            if d[a] > 1e-12 {
                step[a] = 1;
                t_next[a] = (w0[a] + (ijk[a] + 1) as f64 * s - o[a]) / d[a];
                t_delta[a] = s / d[a];
            } else if d[a] < -1e-12 {
                step[a] = -1;
                t_next[a] = (w0[a] + ijk[a] as f64 * s - o[a]) / d[a];
                t_delta[a] = -s / d[a];
            }
        }
        let mut t = t0;
        let mut axis = entry_axis;
        let dims = [
            self.dims[0] as i64,
            self.dims[1] as i64,
            self.dims[2] as i64,
        ];
        loop {
            let l = [ijk[0] as usize, ijk[1] as usize, ijk[2] as usize];
            let bc = [l[0] >> 2, l[1] >> 2, l[2] >> 2];
            let b = (bc[0] * self.bdims[1] + bc[1]) * self.bdims[2] + bc[2];
            if self.bocc[b] == 0 {
                let in_visit = !visit_empty
                    && (0..3).all(|a| (bc[a] as i64) >= vb_lo[a] && (bc[a] as i64) < vb_hi[a]);
                if !in_visit {
                    // skip the rest of this empty brick: find the boundary crossing that leaves it
                    let mut t_exit = f64::INFINITY;
                    let mut a_exit = 3;
                    let mut n_in = [0i64; 3];
                    for a in 0..3 {
                        if step[a] != 0 {
                            n_in[a] = if step[a] > 0 {
                                3 - (ijk[a] & 3)
                            } else {
                                ijk[a] & 3
                            };
                            let te = t_next[a] + n_in[a] as f64 * t_delta[a];
                            if te < t_exit {
                                t_exit = te;
                                a_exit = a;
                            }
                        }
                    }
                    if a_exit == 3 || t_exit > t1 {
                        return None;
                    }
                    for a in 0..3 {
                        if step[a] == 0 {
                            continue;
                        }
                        if a == a_exit {
                            for _ in 0..=n_in[a] {
                                ijk[a] += step[a];
                                t_next[a] += t_delta[a];
                            }
                        } else {
                            while t_next[a] < t_exit {
                                ijk[a] += step[a];
                                t_next[a] += t_delta[a];
                            }
                        }
                    }
                    t = t_exit;
                    axis = a_exit;
                    if (0..3).any(|a| ijk[a] < 0 || ijk[a] >= dims[a]) {
                        return None;
                    }
                    continue;
                }
            }
            let v = if self.bocc[b] == 0 {
                0
            } else {
                self.vox[(b << 6) | ((l[0] & 3) << 4) | ((l[1] & 3) << 2) | (l[2] & 3)]
            };
            if v != 0 {
                let dir_sign = if d[axis] >= 0.0 { 1 } else { -1 };
                return Some(Hit {
                    t,
                    ijk: l,
                    axis,
                    dir_sign,
                    vox: v,
                });
            }
            on_free(l);
            // advance to the nearest boundary
            let a = if t_next[0] <= t_next[1] {
                if t_next[0] <= t_next[2] {
                    0
                } else {
                    2
                }
            } else if t_next[1] <= t_next[2] {
                1
            } else {
                2
            };
            t = t_next[a];
            if t > t1 {
                return None;
            }
            ijk[a] += step[a];
            if ijk[a] < 0 || ijk[a] >= dims[a] {
                return None;
            }
            t_next[a] += t_delta[a];
            axis = a;
        }
    }
}

/// `(min, max)` metric box of a local voxel.
pub(crate) fn voxel_box(world: &World, ijk: [usize; 3]) -> ([f64; 3], [f64; 3]) {
    let w0 = world.min_m();
    let s = world.lattice.voxel_size_m;
    let lo = [0, 1, 2].map(|a| w0[a] + ijk[a] as f64 * s);
    (lo, [lo[0] + s, lo[1] + s, lo[2] + s])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::layout::{Pattern, Prim, Shape};

    fn world_with_box() -> World {
        let lat = Lattice {
            origin_m: [0.0, 0.0, 0.0],
            voxel_size_m: 0.5,
        };
        let mut w = World::new(lat, [0, 0, 0], [20, 10, 6], 1);
        w.rasterize(&Prim {
            shape: Shape::Box {
                c: [5.0, 2.5, 1.0],
                h: [1.0, 1.0, 1.0],
                yaw: 0.0,
            },
            class: 3,
            shade: 0,
            pattern: Pattern::Solid,
        });
        w
    }

    #[test]
    fn rasterize_marks_voxels_with_centres_inside() {
        let w = world_with_box();
        let mut n = 0;
        for i in 0..20 {
            for j in 0..10 {
                for k in 0..6 {
                    let c = [
                        (i as f64 + 0.5) * 0.5,
                        (j as f64 + 0.5) * 0.5,
                        (k as f64 + 0.5) * 0.5,
                    ];
                    let inside = (c[0] - 5.0).abs() <= 1.0
                        && (c[1] - 2.5).abs() <= 1.0
                        && (c[2] - 1.0).abs() <= 1.0;
                    assert_eq!(w.vox[w.index([i, j, k])] != 0, inside, "{i} {j} {k}");
                    n += usize::from(inside);
                }
            }
        }
        assert_eq!(n, 4 * 4 * 4);
    }

    #[test]
    fn thin_primitives_leave_voxels() {
        let lat = Lattice {
            origin_m: [0.0, 0.0, 0.0],
            voxel_size_m: 0.4,
        };
        let mut w = World::new(lat, [0, 0, 0], [10, 10, 10], 1);
        // a 2 cm pole placed on a voxel corner would have no voxel centre inside
        w.rasterize(&Prim {
            shape: Shape::Cyl {
                c: [0.8, 0.8],
                r: 0.02,
                z0: 0.0,
                z1: 3.0,
            },
            class: 18,
            shade: 0,
            pattern: Pattern::Solid,
        });
        let n = w.vox.iter().filter(|&&v| v != 0).count();
        assert!(n >= 7, "pole voxels {n}");
    }

    /// Brute-force reference: march in tiny steps and return the first occupied voxel.
    fn march(w: &World, o: [f64; 3], d: [f64; 3], t_max: f64) -> Option<[usize; 3]> {
        let mut t = 0.0;
        while t < t_max {
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            if let Some(l) = w.local_of_point(p) {
                if w.vox[w.index(l)] != 0 {
                    return Some(l);
                }
            }
            t += 1e-4;
        }
        None
    }

    #[test]
    fn trace_matches_brute_force_marching() {
        let w = world_with_box();
        let mut n_hits = 0;
        for i in 0..200 {
            let a = i as f64 * 0.0314;
            let el = (i % 7) as f64 * 0.05 - 0.15;
            let d = [a.cos() * el.cos(), a.sin() * el.cos(), el.sin()];
            let o = [1.3, 2.6, 1.1];
            let mut free = Vec::new();
            let all = ([0, 0, 0], [20, 10, 6]);
            let h = w.trace(o, d, 30.0, &all, |l| free.push(l));
            let r = march(&w, o, d, 30.0);
            assert_eq!(h.map(|h| h.ijk), r, "ray {i}");
            // skipping empty bricks (nothing to visit) finds the same hit at the same distance
            let h2 = w.trace(o, d, 30.0, &([0, 0, 0], [0, 0, 0]), |_| {});
            assert_eq!(
                h2.map(|h| (h.ijk, h.axis)),
                h.map(|h| (h.ijk, h.axis)),
                "ray {i}"
            );
            if let (Some(a), Some(b)) = (h, h2) {
                assert!((a.t - b.t).abs() < 1e-9);
            }
            // visited voxels are consecutive face neighbours
            for p in free.windows(2) {
                let dist: usize = (0..3).map(|k| p[0][k].abs_diff(p[1][k])).sum();
                assert_eq!(dist, 1);
            }
            if let Some(h) = h {
                n_hits += 1;
                let p = [o[0] + h.t * d[0], o[1] + h.t * d[1], o[2] + h.t * d[2]];
                let (lo, hi) = voxel_box(&w, h.ijk);
                for k in 0..3 {
                    assert!(p[k] >= lo[k] - 1e-9 && p[k] <= hi[k] + 1e-9);
                }
                // the entry face lies on the box boundary of the hit axis
                let face = if h.dir_sign > 0 {
                    lo[h.axis]
                } else {
                    hi[h.axis]
                };
                assert!((p[h.axis] - face).abs() < 1e-9);
            }
            // every traversed voxel is empty and distinct
            for l in &free {
                assert_eq!(w.vox[w.index(*l)], 0);
            }
        }
        assert!(n_hits > 10);
        // a ray from outside the window enters it
        let h = w.trace(
            [-3.0, 2.6, 1.1],
            [1.0, 0.0, 0.0],
            100.0,
            &([0, 0, 0], [0, 0, 0]),
            |_| {},
        );
        assert_eq!(h.map(|h| (h.ijk, h.axis)), Some(([8, 5, 2], 0)));
    }
}
