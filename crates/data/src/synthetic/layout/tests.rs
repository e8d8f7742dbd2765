//! Unit tests of the layout generator: primitive geometry, determinism, the free ego corridor
//! and class coverage.

use super::*;
use crate::synthetic::classes::*;

fn region() -> Region {
    Region {
        lo: [0.0, -25.6, -0.4],
        hi: [51.2, 25.6, 6.0],
    }
}

#[test]
fn shapes_contain_their_skeleton_and_centre() {
    let shapes = [
        Shape::Box {
            c: [1.0, 2.0, 0.5],
            h: [2.0, 0.03, 0.4],
            yaw: 0.7,
        },
        Shape::Cyl {
            c: [0.0, 0.0],
            r: 0.05,
            z0: 0.0,
            z1: 3.0,
        },
        Shape::Ell {
            c: [0.0, 1.0, 2.0],
            r: [1.0, 2.0, 0.5],
        },
    ];
    for s in shapes {
        let (lo, hi) = s.aabb();
        let inflated = match s {
            Shape::Box { c, h, yaw } => Shape::Box {
                c,
                h: h.map(|v| v + 1e-9),
                yaw,
            },
            Shape::Cyl { c, r, z0, z1 } => Shape::Cyl {
                c,
                r: r + 1e-9,
                z0: z0 - 1e-9,
                z1: z1 + 1e-9,
            },
            Shape::Ell { c, r } => Shape::Ell {
                c,
                r: r.map(|v| v * (1.0 + 1e-9)),
            },
        };
        for p in s.skeleton(0.1) {
            assert!(inflated.contains(p), "{s:?} {p:?}");
            for k in 0..3 {
                assert!(p[k] >= lo[k] - 1e-9 && p[k] <= hi[k] + 1e-9);
            }
        }
    }
    // rotated box: brute-force check that contained points are inside the AABB
    let b = Shape::Box {
        c: [0.0, 0.0, 0.0],
        h: [2.0, 1.0, 0.5],
        yaw: 0.4,
    };
    let (lo, hi) = b.aabb();
    for i in -30..=30 {
        for j in -30..=30 {
            let p = [i as f64 * 0.1, j as f64 * 0.1, 0.0];
            if b.contains(p) {
                assert!(p[0] >= lo[0] && p[0] <= hi[0] && p[1] >= lo[1] && p[1] <= hi[1]);
            }
        }
    }
}

#[test]
fn layout_is_deterministic_and_keeps_ego_corridor_free() {
    let a = generate_layout(5, Style::Kitti, -40.0, 200.0, region());
    let b = generate_layout(5, Style::Kitti, -40.0, 200.0, region());
    assert_eq!(a, b);
    let c = generate_layout(6, Style::Kitti, -40.0, 200.0, region());
    assert_ne!(a, c);
    let ey = a.plan.ego_y;
    assert_eq!(a.plan.ground(10.0, ey, 0.1).0, ROAD);
    for o in &a.objects {
        let (lo, hi) = o.aabb();
        assert!(
            hi[1] <= ey - 1.3 || lo[1] >= ey + 1.3 || lo[2] >= 4.5,
            "object in ego corridor: {lo:?} {hi:?}"
        );
    }
}

#[test]
fn every_required_class_is_placed_in_the_region() {
    for seed in 0..20 {
        for style in [Style::Kitti, Style::Nuscenes] {
            let l = generate_layout(seed, style, -40.0, 200.0, region());
            let r = region();
            let r = Region {
                lo: [r.lo[0], r.lo[1] + l.plan.ego_y, r.lo[2]],
                hi: [r.hi[0], r.hi[1] + l.plan.ego_y, r.hi[2]],
            };
            for cls in required_object_classes(style) {
                let found = l.objects.iter().any(|o| {
                    o.prims
                        .iter()
                        .any(|p| p.class == cls && overlaps(&p.shape.aabb(), &(r.lo, r.hi)))
                });
                assert!(found, "seed {seed} style {style:?} class {cls}");
            }
            for cls in [ROAD, PARKING, SIDEWALK, OTHER_GROUND, TERRAIN] {
                let mut found = false;
                for xi in 0..50 {
                    for yi in 0..100 {
                        if l.plan
                            .ground(xi as f64 + 0.5, r.lo[1] + yi as f64 * 0.5, 0.1)
                            .0
                            == cls
                        {
                            found = true;
                        }
                    }
                }
                assert!(found, "seed {seed} ground class {cls}");
            }
        }
    }
}
