//! The town's outside façade corners: vertical edges where two faces of a building meet with
//! nothing but those two faces around them, the corners a surveyor measures as control.

use super::Town;
use crate::truth::SurfaceClass;
use std::collections::BTreeSet;

/// Around a corner, within this radius, the two faces must be whole (no window, relief or
/// neighbour) and nothing else may stand: the radius within which the estimator's surfaces
/// observe a control point.
pub const CORNER_CLEAR_M: f64 = 0.5;

/// Depth behind and in front of a face at which solidity is probed, metres.
const PROBE_M: f64 = 0.01;

/// An outside corner of a building at one height: the point on its vertical edge and the two
/// faces that meet there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FacadeCorner {
    /// Local position on the edge.
    pub position: [f64; 3],
    /// Surface id and world outward unit normal of each face; both faces pass through `position`.
    pub faces: [(u32, [f64; 3]); 2],
}

impl Town {
    /// Every outside façade corner at height `z_above_ground` above the ground plane (the sheared
    /// frame's `z'`, so the sidewalk's top is at the curb height), in the order the buildings
    /// were built. A corner qualifies when, within [`CORNER_CLEAR_M`] of it (horizontally and
    /// vertically), the building is solid behind both faces and everything in front of them is
    /// free: a wall corner, not one beside a window, a pilaster or a neighbouring building.
    pub fn facade_corners(&self, z_above_ground: f64) -> Vec<FacadeCorner> {
        let z = z_above_ground;
        let mut seen = BTreeSet::new();
        let mut out = Vec::new();
        for b in &self.boxes {
            if self.surfaces[b.id0 as usize].class != SurfaceClass::Facade
                || z < b.min[2] + CORNER_CLEAR_M
                || z > b.max[2] - CORNER_CLEAR_M
            {
                continue;
            }
            for (ex, sx, fx) in [(b.min[0], -1.0, 0), (b.max[0], 1.0, 1)] {
                for (ey, sy, fy) in [(b.min[1], -1.0, 2), (b.max[1], 1.0, 3)] {
                    let key = ((ex * 1e6).round() as i64, (ey * 1e6).round() as i64);
                    if seen.contains(&key) || !self.is_clear_corner([ex, ey, z], sx, sy) {
                        continue;
                    }
                    seen.insert(key);
                    let y = ey;
                    let x = ex + self.skew * y;
                    let position = [x, y, z + self.grade[0] * x + self.grade[1] * y];
                    out.push(FacadeCorner {
                        position,
                        faces: [
                            (b.id0 + fx, self.world_normal([sx, 0.0, 0.0])),
                            (b.id0 + fy, self.world_normal([0.0, sy, 0.0])),
                        ],
                    });
                }
            }
        }
        out
    }

    /// Whether the sheared-frame vertical edge through `q`, with the solid on the `−sx`, `−sy`
    /// side, is a clear outside corner: solid just behind both faces and inside, free in front of
    /// them and around the corner, everywhere within [`CORNER_CLEAR_M`].
    fn is_clear_corner(&self, q: [f64; 3], sx: f64, sy: f64) -> bool {
        let e = PROBE_M;
        let reach = CORNER_CLEAR_M - e;
        let solid = |dx: f64, dy: f64, dz: f64| self.solid_at_sheared([q[0] + sx * dx, q[1] + sy * dy, q[2] + dz]);
        for dz in [-reach, -reach / 2.0, 0.0, reach / 2.0, reach] {
            for r in [2.0 * e, 0.1, 0.25, 0.4, reach] {
                let inside = [(-e, -r), (-r, -e), (-0.7 * r, -0.7 * r)];
                let outside = [(e, -r), (r, -r), (-r, e), (-r, r), (r, r), (r, e), (e, r)];
                if inside.iter().any(|&(dx, dy)| solid(dx, dy, dz).is_none())
                    || outside.iter().any(|&(dx, dy)| solid(dx, dy, dz).is_some())
                {
                    return false;
                }
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TownConfig;

    #[test]
    fn corners_lie_on_both_faces_with_a_clear_wall_around() {
        for skew_deg in [0.0, 25.0] {
            let cfg = TownConfig { skew_deg, ..TownConfig::default() };
            let town = Town::build(&cfg, 5);
            let corners = town.facade_corners(cfg.curb_height_m + 1.5);
            // Every block has four corners; gaps between buildings add more.
            let blocks = (cfg.blocks_x + 2) * (cfg.blocks_y + 2);
            assert!(corners.len() >= 2 * blocks as usize, "{skew_deg}°: {} corners", corners.len());
            for c in &corners {
                let [(a, na), (b, nb)] = c.faces;
                for id in [a, b] {
                    let check = town.check_surface(id, c.position, 1e-9).unwrap();
                    assert!(check.distance.abs() < 1e-9 && check.within_bounds, "{c:?}: {check:?}");
                    assert_eq!(town.surface(id).unwrap().class, SurfaceClass::Facade);
                }
                let dot = na[0] * nb[0] + na[1] * nb[1] + na[2] * nb[2];
                assert!(dot.abs() < 0.5 && na[2].abs() < 1e-9, "{c:?}");
                // Just in front of either face and diagonally out there is air, behind it wall.
                for (dir, air) in [(na, true), (nb, true), ([-na[0] - nb[0], -na[1] - nb[1], 0.0], false)] {
                    let p = [0, 1, 2].map(|k| c.position[k] + 0.02 * dir[k]);
                    assert_eq!(town.solid_at(p).is_none(), air, "{c:?} at {p:?}");
                }
            }
        }
    }
}
