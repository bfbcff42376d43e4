//! The simulated town and a fast ray caster over it.
//!
//! Geometry lives in local coordinates (metres from [`SimConfig::origin`](crate::SimConfig)),
//! with the ground sloping as `z = a·x + b·y`. Everything is built in the *sheared* frame
//! `z' = z − a·x − b·y`, where the ground is `z' = 0` and every box is axis-aligned. The shear is
//! linear, so a ray stays a ray with the same parameter `t` (world metres along a unit world
//! direction); world normals are the sheared normals times the shear's transpose, normalised.
//!
//! Primitives: axis-aligned boxes (sidewalk slabs whose sides are the curbs, buildings, façade
//! relief, cars), vertical cylinders (poles, tree trunks) and spheres (tree crowns, which are
//! volumetric clutter: a ray inside hits with a per-metre probability). A uniform 2D grid holds the
//! primitives overlapping each cell; a ray walks the grid in order (2D DDA) and stops once the
//! nearest hit lies inside the cells already visited.

use crate::config::TownConfig;
use crate::rng::{self, Rng};
use crate::truth::SurfaceClass;

const T_EPS: f64 = 1e-7;
const STREAM_TOWN: u64 = 0x7017_0000;
/// Surface id of the ground (road) plane; ids start at 1 so 0 can mean "none".
pub const GROUND_ID: u32 = 1;

/// The street grid: street centre lines at `x = (i − blocks_x/2)·L` and `y = (j − blocks_y/2)·L`.
/// Lines `0..=blocks_x` (`0..=blocks_y`) enclose the driven blocks; one ring of blocks more is built.
/// Coordinates are those of the grid frame; [`Layout::to_world`] maps them to local metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Layout {
    pub blocks_x: u32,
    pub blocks_y: u32,
    pub block_m: f64,
    /// `tan(skew)`: the grid frame's y axis leans by the skew towards +x in the world.
    pub skew: f64,
}

impl Layout {
    /// A right-angled grid.
    pub fn square(blocks_x: u32, blocks_y: u32, block_m: f64) -> Layout {
        Layout { blocks_x, blocks_y, block_m, skew: 0.0 }
    }

    /// World (local) x, y of grid-frame point `p`.
    pub fn to_world(&self, p: [f64; 2]) -> [f64; 2] {
        [p[0] + self.skew * p[1], p[1]]
    }

    pub fn street_x(&self, i: i32) -> f64 {
        (i as f64 - self.blocks_x as f64 / 2.0) * self.block_m
    }

    pub fn street_y(&self, j: i32) -> f64 {
        (j as f64 - self.blocks_y as f64 / 2.0) * self.block_m
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum BoxKind {
    /// Raised sidewalk of a block: sides are curbs, top is sidewalk.
    Slab,
    /// Building body: sides façade (the window plane), top roof.
    Building,
    /// Façade relief (piers, bands, pilasters, oriels).
    Detail,
    Car,
}

#[derive(Clone, Copy, Debug)]
struct BoxPrim {
    min: [f64; 3],
    max: [f64; 3],
    /// Faces −x, +x, −y, +y, −z, +z have ids `id0 .. id0 + 6`.
    id0: u32,
}

/// Vertical cylinder (sheared frame); side id `id`, top cap `id + 1`.
#[derive(Clone, Copy, Debug)]
struct CylPrim {
    c: [f64; 2],
    r: f64,
    z0: f64,
    z1: f64,
    id: u32,
}

/// Tree crown (sphere in the sheared frame).
#[derive(Clone, Copy, Debug)]
struct CrownPrim {
    c: [f64; 3],
    r: f64,
    id: u32,
}

/// What a surface id refers to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    Ground,
    /// Face `face` (−x, +x, −y, +y, −z, +z) of box `prim`.
    BoxFace {
        prim: u32,
        face: u8,
    },
    CylinderSide {
        prim: u32,
    },
    CylinderCap {
        prim: u32,
    },
    Crown {
        prim: u32,
    },
}

/// One surface of the town: every planar face and every object has its own id.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Surface {
    pub class: SurfaceClass,
    pub shape: Shape,
}

/// The nearest hit of a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction, metres.
    pub t: f64,
    /// Geometric outward unit normal in the world frame (random for foliage).
    pub normal: [f64; 3],
    pub surface_id: u32,
    pub class: SurfaceClass,
}

/// How far a point is from a surface: signed distance along the outward normal (for a crown: from
/// the sphere, negative inside) and whether it lies within the surface's bounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceCheck {
    pub distance: f64,
    pub within_bounds: bool,
}

#[derive(Clone, Copy, Debug)]
enum HitRef {
    None,
    Ground,
    Box(u32, u8),
    CylSide(u32, [f64; 2]),
    CylCap(u32),
    Crown(u32),
}

#[derive(Clone, Copy, Debug)]
struct Best {
    t: f64,
    what: HitRef,
}

const KIND_BITS: u32 = 30;
const KIND_BOX: u32 = 0;
const KIND_CYL: u32 = 1;
const KIND_CROWN: u32 = 2;

/// Uniform 2D grid, cells as a compressed list of primitive references.
#[derive(Clone, Debug)]
struct Grid {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: i64,
    ny: i64,
    start: Vec<u32>,
    items: Vec<u32>,
}

/// Statistics of a built town.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct TownStats {
    pub boxes: usize,
    pub cylinders: usize,
    pub crowns: usize,
    pub surfaces: usize,
    pub buildings: usize,
    pub cars: usize,
    pub poles: usize,
    pub trees: usize,
    pub grid_cells: usize,
    pub grid_references: usize,
}

#[derive(Debug)]
pub struct Town {
    layout: Layout,
    grade: [f64; 2],
    /// `tan(skew)` of the street grid: the sheared frame's x is `x − skew·y`.
    skew: f64,
    /// |(−a, −b, 1)|, the length of the shear-transformed z normal.
    slope_norm: f64,
    mean_free_path: f64,
    boxes: Vec<BoxPrim>,
    cyls: Vec<CylPrim>,
    crowns: Vec<CrownPrim>,
    /// Indexed by surface id (index 0 unused).
    surfaces: Vec<Surface>,
    grid: Grid,
    /// Highest z' of any primitive: a rising ray above it can hit nothing more.
    z_top: f64,
    stats: TownStats,
}

/// Maps façade-local coordinates (u along the façade, w outward from the façade line) to x, y.
#[derive(Clone, Copy, Debug)]
struct SideFrame {
    origin: [f64; 2],
    u_dir: [f64; 2],
    w_dir: [f64; 2],
}

impl SideFrame {
    fn point(&self, u: f64, w: f64) -> [f64; 2] {
        [self.origin[0] + u * self.u_dir[0] + w * self.w_dir[0], self.origin[1] + u * self.u_dir[1] + w * self.w_dir[1]]
    }

    /// Axis-aligned xy bounds of the façade-local rectangle `[u0, u1] × [w0, w1]`.
    fn rect(&self, u0: f64, u1: f64, w0: f64, w1: f64) -> ([f64; 2], [f64; 2]) {
        let a = self.point(u0, w0);
        let b = self.point(u1, w1);
        ([a[0].min(b[0]), a[1].min(b[1])], [a[0].max(b[0]), a[1].max(b[1])])
    }
}

struct Builder<'a> {
    cfg: &'a TownConfig,
    rng: Rng,
    boxes: Vec<BoxPrim>,
    cyls: Vec<CylPrim>,
    crowns: Vec<CrownPrim>,
    surfaces: Vec<Surface>,
    buildings: usize,
    cars: usize,
    poles: usize,
    trees: usize,
}

impl Builder<'_> {
    fn add_box(&mut self, min: [f64; 3], max: [f64; 3], kind: BoxKind) {
        let id0 = self.surfaces.len() as u32;
        let prim = self.boxes.len() as u32;
        for face in 0..6u8 {
            let class = match (kind, face) {
                (BoxKind::Slab, 5) => SurfaceClass::Sidewalk,
                (BoxKind::Slab, _) => SurfaceClass::Curb,
                (BoxKind::Building, 5) => SurfaceClass::Roof,
                (BoxKind::Building | BoxKind::Detail, _) => SurfaceClass::Facade,
                (BoxKind::Car, _) => SurfaceClass::Car,
            };
            self.surfaces.push(Surface { class, shape: Shape::BoxFace { prim, face } });
        }
        self.boxes.push(BoxPrim { min, max, id0 });
    }

    fn add_side_box(&mut self, f: &SideFrame, u: [f64; 2], w: [f64; 2], z: [f64; 2], kind: BoxKind) {
        let (lo, hi) = f.rect(u[0], u[1], w[0], w[1]);
        self.add_box([lo[0], lo[1], z[0]], [hi[0], hi[1], z[1]], kind);
    }

    fn add_cylinder(&mut self, c: [f64; 2], r: f64, z0: f64, z1: f64) {
        let id = self.surfaces.len() as u32;
        let prim = self.cyls.len() as u32;
        self.surfaces.push(Surface { class: SurfaceClass::Pole, shape: Shape::CylinderSide { prim } });
        self.surfaces.push(Surface { class: SurfaceClass::Pole, shape: Shape::CylinderCap { prim } });
        self.cyls.push(CylPrim { c, r, z0, z1, id });
    }

    fn add_crown(&mut self, c: [f64; 3], r: f64) {
        let id = self.surfaces.len() as u32;
        let prim = self.crowns.len() as u32;
        self.surfaces.push(Surface { class: SurfaceClass::Foliage, shape: Shape::Crown { prim } });
        self.crowns.push(CrownPrim { c, r, id });
    }

    /// One block between street lines `xa..xb`, `ya..yb`.
    fn block(&mut self, xa: f64, xb: f64, ya: f64, yb: f64) {
        let c = self.cfg;
        let rhw = c.road_half_width_m;
        let sw = c.sidewalk_width_m;
        let f = rhw + sw;
        self.add_box([xa + rhw, ya + rhw, 0.0], [xb - rhw, yb - rhw, c.curb_height_m], BoxKind::Slab);
        let ix = xb - xa - 2.0 * f;
        let iy = yb - ya - 2.0 * f;
        let depth_x = c.building_depth_m.min(iy / 2.0 - 0.5).max(2.0);
        let depth_y = c.building_depth_m.min(ix / 2.0 - 0.5).max(2.0);
        // South and north rows span the whole side; west and east rows fit between them.
        let sides = [
            (SideFrame { origin: [xa + f, ya + f], u_dir: [1.0, 0.0], w_dir: [0.0, -1.0] }, ix, 0.0, ix, depth_x),
            (SideFrame { origin: [xb - f, yb - f], u_dir: [-1.0, 0.0], w_dir: [0.0, 1.0] }, ix, 0.0, ix, depth_x),
            (
                SideFrame { origin: [xa + f, yb - f], u_dir: [0.0, -1.0], w_dir: [-1.0, 0.0] },
                iy,
                depth_x,
                iy - depth_x,
                depth_y,
            ),
            (
                SideFrame { origin: [xb - f, ya + f], u_dir: [0.0, 1.0], w_dir: [1.0, 0.0] },
                iy,
                depth_x,
                iy - depth_x,
                depth_y,
            ),
        ];
        for (frame, len, ua, ub, depth) in sides {
            self.buildings_along(&frame, ua, ub, depth);
            self.street_furniture(&frame, len);
        }
    }

    fn buildings_along(&mut self, frame: &SideFrame, ua: f64, ub: f64, depth: f64) {
        let c = self.cfg;
        let mut u = ua;
        while ub - u > 4.0 {
            if self.rng.chance(c.gap_probability) {
                u += self.rng.within(c.gap_width_m);
                continue;
            }
            let mut w = self.rng.within(c.building_width_m);
            if ub - (u + w) < c.building_width_m[0] * 0.75 {
                w = ub - u; // absorb the remainder rather than leave a sliver
            }
            self.building(frame, u, u + w, depth);
            u += w;
        }
    }

    fn building(&mut self, frame: &SideFrame, u0: f64, u1: f64, depth: f64) {
        let c = self.cfg;
        self.buildings += 1;
        let base = c.curb_height_m;
        let top = base + self.rng.within(c.building_height_m);
        let recess = self.rng.within(c.window_recess_m);
        let floor = self.rng.within(c.floor_height_m);
        let bay = self.rng.within(c.bay_m);
        let ww = self.rng.within(c.window_width_m).min(bay - 0.5);
        let wh = self.rng.within(c.window_height_m).min(floor - 0.8);
        let sill = self.rng.range(0.8, 1.0).min(floor - wh - 0.3);
        // Body: its front face is the window plane, `recess` behind the façade line.
        self.add_side_box(frame, [u0, u1], [-depth, -recess], [base, top], BoxKind::Building);
        // Wall layer in front of it, with holes where the windows are (piers and bands overlap
        // the body slightly so there is no crack).
        let wall = [-recess - 0.02, 0.0];
        let width = u1 - u0;
        let cols = ((width - 0.6) / bay).floor().max(0.0) as usize;
        let mut rows = 0;
        while base + rows as f64 * floor + sill + wh <= top - 0.5 {
            rows += 1;
        }
        if cols == 0 || rows == 0 {
            self.add_side_box(frame, [u0, u1], wall, [base, top], BoxKind::Detail);
        } else {
            let margin = (width - cols as f64 * bay) / 2.0;
            let mut left = u0;
            for k in 0..cols {
                let centre = u0 + margin + (k as f64 + 0.5) * bay;
                self.add_side_box(frame, [left, centre - ww / 2.0], wall, [base, top], BoxKind::Detail);
                left = centre + ww / 2.0;
            }
            self.add_side_box(frame, [left, u1], wall, [base, top], BoxKind::Detail);
            let mut bottom = base;
            for r in 0..rows {
                let sill_z = base + r as f64 * floor + sill;
                self.add_side_box(frame, [u0, u1], wall, [bottom, sill_z], BoxKind::Detail);
                bottom = sill_z + wh;
            }
            self.add_side_box(frame, [u0, u1], wall, [bottom, top], BoxKind::Detail);
        }
        if self.rng.chance(0.35) {
            let p = self.rng.within(c.relief_m);
            self.add_side_box(frame, [u0, u0 + 0.45], [-0.05, p], [base, top], BoxKind::Detail);
            self.add_side_box(frame, [u1 - 0.45, u1], [-0.05, p], [base, top], BoxKind::Detail);
        }
        if width > 8.0 && top - base > floor + 3.0 && self.rng.chance(0.3) {
            let p = self.rng.within(c.relief_m);
            let ow = self.rng.range(2.0, 3.5);
            let oc = self.rng.range(u0 + 1.0 + ow / 2.0, u1 - 1.0 - ow / 2.0);
            self.add_side_box(
                frame,
                [oc - ow / 2.0, oc + ow / 2.0],
                [-0.05, p],
                [base + floor, top - 0.3],
                BoxKind::Detail,
            );
        }
    }

    /// Poles, trees and parked cars on the sidewalk in front of a façade of length `len`.
    fn street_furniture(&mut self, frame: &SideFrame, len: f64) {
        let c = self.cfg;
        let sw = c.sidewalk_width_m;
        let base = c.curb_height_m;
        let (ua, ub) = (-sw + c.corner_clearance_m, len + sw - c.corner_clearance_m);
        if ub - ua < 2.0 {
            return;
        }
        // Street lights 0.3 m behind the curb.
        let spacing = c.pole_spacing_m;
        let mut u = ua + self.rng.range(0.0, spacing.min(ub - ua));
        let mut poles = Vec::new();
        while u <= ub {
            let h = self.rng.within(c.pole_height_m);
            self.add_cylinder(frame.point(u, sw - 0.3), c.pole_radius_m, base, base + h);
            self.poles += 1;
            poles.push(u);
            u += spacing + self.rng.range(-1.0, 1.0);
        }
        // Trees in regular slots 1.2 m in front of the façade, planted at random, clear of poles.
        let mut u = ua + self.rng.range(0.0, c.tree_spacing_m.min(ub - ua));
        while u <= ub {
            if self.rng.chance(c.tree_probability) && poles.iter().all(|p| (p - u).abs() > 2.5) {
                self.tree(frame.point(u, 1.2));
            }
            u += c.tree_spacing_m;
        }
        // Cars parked mostly on the sidewalk (German style), their outer side 0.45 m over the
        // curb; not where a street light stands.
        let slot = 6.5;
        let mut u = ua;
        while u + slot <= ub {
            let centre = u + slot / 2.0;
            if self.rng.chance(c.car_probability) && poles.iter().all(|p| (p - centre).abs() > 3.0) {
                self.car(frame, centre, sw - 0.45);
            }
            u += slot;
        }
    }

    fn tree(&mut self, at: [f64; 2]) {
        let c = self.cfg;
        let r = self.rng.within(c.crown_radius_m);
        let zc = c.curb_height_m + self.rng.within(c.crown_height_m).max(r + 2.2);
        let trunk = self.rng.within(c.trunk_radius_m);
        self.add_cylinder(at, trunk, c.curb_height_m, zc);
        self.add_crown([at[0], at[1], zc], r);
        self.trees += 1;
    }

    fn car(&mut self, frame: &SideFrame, u: f64, w: f64) {
        let len = self.rng.range(4.1, 4.8);
        let wid = self.rng.range(1.7, 1.9);
        let roof = self.rng.range(1.35, 1.55);
        let shoulder = self.rng.range(0.85, 1.0);
        self.add_side_box(
            frame,
            [u - len / 2.0, u + len / 2.0],
            [w - wid / 2.0, w + wid / 2.0],
            [0.3, shoulder],
            BoxKind::Car,
        );
        let cl = len * 0.55;
        let back = u - len / 2.0 + len * 0.15;
        self.add_side_box(
            frame,
            [back, back + cl],
            [w - wid / 2.0 + 0.1, w + wid / 2.0 - 0.1],
            [shoulder, roof],
            BoxKind::Car,
        );
        self.cars += 1;
    }
}

impl Town {
    /// Builds the town of `cfg`, randomised by `seed`.
    pub fn build(cfg: &TownConfig, seed: u64) -> Town {
        let skew = cfg.skew_deg.to_radians().tan();
        let layout = Layout { blocks_x: cfg.blocks_x, blocks_y: cfg.blocks_y, block_m: cfg.block_m, skew };
        let mut b = Builder {
            cfg,
            rng: Rng::new(seed, STREAM_TOWN),
            boxes: Vec::new(),
            cyls: Vec::new(),
            crowns: Vec::new(),
            surfaces: vec![
                Surface { class: SurfaceClass::Road, shape: Shape::Ground },
                Surface { class: SurfaceClass::Road, shape: Shape::Ground },
            ],
            buildings: 0,
            cars: 0,
            poles: 0,
            trees: 0,
        };
        for j in -1..=cfg.blocks_y as i32 {
            for i in -1..=cfg.blocks_x as i32 {
                b.block(layout.street_x(i), layout.street_x(i + 1), layout.street_y(j), layout.street_y(j + 1));
            }
        }
        let [a, g] = cfg.grade;
        let mut z_top: f64 = 0.0;
        let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let mut footprints = Vec::new();
        for (k, bx) in b.boxes.iter().enumerate() {
            z_top = z_top.max(bx.max[2]);
            footprints.push(((KIND_BOX << KIND_BITS) | k as u32, [bx.min[0], bx.min[1], bx.max[0], bx.max[1]]));
        }
        for (k, cy) in b.cyls.iter().enumerate() {
            z_top = z_top.max(cy.z1);
            let fp = [cy.c[0] - cy.r, cy.c[1] - cy.r, cy.c[0] + cy.r, cy.c[1] + cy.r];
            footprints.push(((KIND_CYL << KIND_BITS) | k as u32, fp));
        }
        for (k, cr) in b.crowns.iter().enumerate() {
            z_top = z_top.max(cr.c[2] + cr.r);
            let fp = [cr.c[0] - cr.r, cr.c[1] - cr.r, cr.c[0] + cr.r, cr.c[1] + cr.r];
            footprints.push(((KIND_CROWN << KIND_BITS) | k as u32, fp));
        }
        for (_, fp) in &footprints {
            bounds = [bounds[0].min(fp[0]), bounds[1].min(fp[1]), bounds[2].max(fp[2]), bounds[3].max(fp[3])];
        }
        let cell = cfg.grid_cell_m;
        let (x0, y0) = ((bounds[0] / cell).floor() * cell - cell, (bounds[1] / cell).floor() * cell - cell);
        let nx = ((bounds[2] - x0) / cell).ceil() as i64 + 1;
        let ny = ((bounds[3] - y0) / cell).ceil() as i64 + 1;
        let mut lists: Vec<Vec<u32>> = vec![Vec::new(); (nx * ny) as usize];
        for (item, fp) in &footprints {
            let cx0 = (((fp[0] - x0) / cell).floor() as i64).clamp(0, nx - 1);
            let cy0 = (((fp[1] - y0) / cell).floor() as i64).clamp(0, ny - 1);
            let cx1 = (((fp[2] - x0) / cell).floor() as i64).clamp(0, nx - 1);
            let cy1 = (((fp[3] - y0) / cell).floor() as i64).clamp(0, ny - 1);
            for cy in cy0..=cy1 {
                for cx in cx0..=cx1 {
                    lists[(cy * nx + cx) as usize].push(*item);
                }
            }
        }
        let mut start = Vec::with_capacity(lists.len() + 1);
        let mut items = Vec::new();
        for l in &lists {
            start.push(items.len() as u32);
            items.extend_from_slice(l);
        }
        start.push(items.len() as u32);
        let stats = TownStats {
            boxes: b.boxes.len(),
            cylinders: b.cyls.len(),
            crowns: b.crowns.len(),
            surfaces: b.surfaces.len() - 1,
            buildings: b.buildings,
            cars: b.cars,
            poles: b.poles,
            trees: b.trees,
            grid_cells: lists.len(),
            grid_references: items.len(),
        };
        Town {
            layout,
            grade: [a, g],
            skew,
            slope_norm: (1.0 + a * a + g * g).sqrt(),
            mean_free_path: cfg.foliage_mean_free_path_m,
            boxes: b.boxes,
            cyls: b.cyls,
            crowns: b.crowns,
            surfaces: b.surfaces,
            grid: Grid { x0, y0, cell, nx, ny, start, items },
            z_top: z_top + 0.01,
            stats,
        }
    }

    pub fn layout(&self) -> Layout {
        self.layout
    }

    pub fn stats(&self) -> TownStats {
        self.stats
    }

    /// Ground height (road level) at local `(x, y)`.
    pub fn ground_z(&self, x: f64, y: f64) -> f64 {
        self.grade[0] * x + self.grade[1] * y
    }

    pub fn grade(&self) -> [f64; 2] {
        self.grade
    }

    /// The surface with id `id`, if it exists.
    pub fn surface(&self, id: u32) -> Option<Surface> {
        (id >= GROUND_ID).then(|| self.surfaces.get(id as usize).copied()).flatten()
    }

    /// All surface ids with their surfaces.
    pub fn surfaces(&self) -> impl Iterator<Item = (u32, Surface)> + '_ {
        self.surfaces.iter().enumerate().skip(1).map(|(i, s)| (i as u32, *s))
    }

    /// The sheared frame of world point (or direction) `p`: the ground becomes `z' = 0` and the
    /// skewed street grid axis-aligned.
    #[inline]
    fn shear(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0] - self.skew * p[1], p[1], p[2] - self.grade[0] * p[0] - self.grade[1] * p[1]]
    }

    /// World unit normal of a sheared-frame normal (the shear's transpose applied, normalised).
    #[inline]
    fn world_normal(&self, n: [f64; 3]) -> [f64; 3] {
        let w = [n[0] - self.grade[0] * n[2], n[1] - self.skew * n[0] - self.grade[1] * n[2], n[2]];
        let l = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        [w[0] / l, w[1] / l, w[2] / l]
    }

    /// Signed distance of local point `p` from surface `id` and whether `p` lies within the
    /// surface's bounds (tolerance `tol` metres). `None` for an unknown id.
    pub fn check_surface(&self, id: u32, p: [f64; 3], tol: f64) -> Option<SurfaceCheck> {
        let s = self.surface(id)?;
        let q = self.shear(p);
        let inside = |v: f64, lo: f64, hi: f64| v >= lo - tol && v <= hi + tol;
        Some(match s.shape {
            Shape::Ground => SurfaceCheck { distance: q[2] / self.slope_norm, within_bounds: true },
            Shape::BoxFace { prim, face } => {
                let b = &self.boxes[prim as usize];
                let axis = (face / 2) as usize;
                let (value, sign) = if face % 2 == 0 { (b.min[axis], -1.0) } else { (b.max[axis], 1.0) };
                let scale = match axis {
                    0 => (1.0 + self.skew * self.skew).sqrt(),
                    1 => 1.0,
                    _ => self.slope_norm,
                };
                let within = (0..3).filter(|&k| k != axis).all(|k| inside(q[k], b.min[k], b.max[k]));
                SurfaceCheck { distance: sign * (q[axis] - value) / scale, within_bounds: within }
            }
            Shape::CylinderSide { prim } => {
                let c = &self.cyls[prim as usize];
                let r = ((q[0] - c.c[0]).powi(2) + (q[1] - c.c[1]).powi(2)).sqrt();
                SurfaceCheck { distance: r - c.r, within_bounds: inside(q[2], c.z0, c.z1) }
            }
            Shape::CylinderCap { prim } => {
                let c = &self.cyls[prim as usize];
                let r = ((q[0] - c.c[0]).powi(2) + (q[1] - c.c[1]).powi(2)).sqrt();
                SurfaceCheck { distance: (q[2] - c.z1) / self.slope_norm, within_bounds: r <= c.r + tol }
            }
            Shape::Crown { prim } => {
                let c = &self.crowns[prim as usize];
                let d = ((q[0] - c.c[0]).powi(2) + (q[1] - c.c[1]).powi(2) + (q[2] - c.c[2]).powi(2)).sqrt();
                SurfaceCheck { distance: d - c.r, within_bounds: d <= c.r + tol }
            }
        })
    }

    /// The first surface id of a solid primitive (box or cylinder; crowns are not solid) that
    /// contains local point `p`, if any. Used to check that vehicles drive through free space.
    pub fn solid_at(&self, p: [f64; 3]) -> Option<u32> {
        self.solid_at_sheared(self.shear(p))
    }

    fn solid_at_sheared(&self, q: [f64; 3]) -> Option<u32> {
        if q[2] < 0.0 {
            return Some(GROUND_ID);
        }
        let g = &self.grid;
        let ix = ((q[0] - g.x0) / g.cell).floor() as i64;
        let iy = ((q[1] - g.y0) / g.cell).floor() as i64;
        if ix < 0 || iy < 0 || ix >= g.nx || iy >= g.ny {
            return None;
        }
        let c = (iy * g.nx + ix) as usize;
        g.items[g.start[c] as usize..g.start[c + 1] as usize].iter().find_map(|&item| {
            let k = (item & ((1 << KIND_BITS) - 1)) as usize;
            match item >> KIND_BITS {
                KIND_BOX => {
                    let b = &self.boxes[k];
                    (0..3).all(|a| q[a] > b.min[a] && q[a] < b.max[a]).then_some(b.id0)
                }
                KIND_CYL => {
                    let cy = &self.cyls[k];
                    let r2 = (q[0] - cy.c[0]).powi(2) + (q[1] - cy.c[1]).powi(2);
                    (r2 < cy.r * cy.r && q[2] > cy.z0 && q[2] < cy.z1).then_some(cy.id)
                }
                _ => None,
            }
        })
    }

    /// Nearest hit of the ray `o + t·d` (local coordinates, `d` a unit vector) with `t ≤ t_max`.
    /// `key` seeds the ray's foliage randomness: the same key gives the same answer.
    pub fn cast(&self, o: [f64; 3], d: [f64; 3], t_max: f64, key: u64) -> Option<Hit> {
        let op = self.shear(o);
        let dp = self.shear(d);
        let mut best = Best { t: t_max, what: HitRef::None };
        if dp[2] < 0.0 && op[2] > 0.0 {
            let t = -op[2] / dp[2];
            if t < best.t {
                best = Best { t, what: HitRef::Ground };
            }
        }
        let t_top = if dp[2] > 0.0 { (self.z_top - op[2]) / dp[2] } else { f64::INFINITY };
        self.walk_grid(&op, &dp, t_top, key, &mut best);
        let (id, normal) = match best.what {
            HitRef::None => return None,
            HitRef::Ground => (GROUND_ID, self.world_normal([0.0, 0.0, 1.0])),
            HitRef::Box(k, face) => {
                let axis = (face / 2) as usize;
                let mut n = [0.0; 3];
                n[axis] = if face % 2 == 0 { -1.0 } else { 1.0 };
                (self.boxes[k as usize].id0 + face as u32, self.world_normal(n))
            }
            HitRef::CylSide(k, n) if self.skew == 0.0 => (self.cyls[k as usize].id, [n[0], n[1], 0.0]),
            HitRef::CylSide(k, n) => (self.cyls[k as usize].id, self.world_normal([n[0], n[1], 0.0])),
            HitRef::CylCap(k) => (self.cyls[k as usize].id + 1, self.world_normal([0.0, 0.0, 1.0])),
            HitRef::Crown(k) => {
                let id = self.crowns[k as usize].id;
                (id, rng::unit_vector(rng::hash3(key, id as u64, 0xF011)))
            }
        };
        Some(Hit { t: best.t, normal, surface_id: id, class: self.surfaces[id as usize].class })
    }

    /// 2D DDA over the grid cells the ray's footprint crosses, nearest first.
    fn walk_grid(&self, op: &[f64; 3], dp: &[f64; 3], t_top: f64, key: u64, best: &mut Best) {
        let g = &self.grid;
        let hi = [g.x0 + g.nx as f64 * g.cell, g.y0 + g.ny as f64 * g.cell];
        let lo = [g.x0, g.y0];
        let (mut t0, mut t1) = (0.0f64, best.t.min(t_top));
        for k in 0..2 {
            if dp[k].abs() < 1e-15 {
                if op[k] < lo[k] || op[k] > hi[k] {
                    return;
                }
            } else {
                let (a, b) = ((lo[k] - op[k]) / dp[k], (hi[k] - op[k]) / dp[k]);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
        }
        if t0 > t1 {
            return;
        }
        let px = op[0] + t0 * dp[0];
        let py = op[1] + t0 * dp[1];
        let mut ix = (((px - g.x0) / g.cell).floor() as i64).clamp(0, g.nx - 1);
        let mut iy = (((py - g.y0) / g.cell).floor() as i64).clamp(0, g.ny - 1);
        let axis_setup = |d: f64, o: f64, i: i64, origin: f64| -> (i64, f64, f64) {
            if d > 1e-15 {
                (1, (origin + (i + 1) as f64 * g.cell - o) / d, g.cell / d)
            } else if d < -1e-15 {
                (-1, (origin + i as f64 * g.cell - o) / d, -g.cell / d)
            } else {
                (0, f64::INFINITY, f64::INFINITY)
            }
        };
        let (sx, mut tx, dtx) = axis_setup(dp[0], op[0], ix, g.x0);
        let (sy, mut ty, dty) = axis_setup(dp[1], op[1], iy, g.y0);
        let inv = [1.0 / dp[0], 1.0 / dp[1], 1.0 / dp[2]];
        loop {
            let c = (iy * g.nx + ix) as usize;
            for &item in &g.items[g.start[c] as usize..g.start[c + 1] as usize] {
                let k = item & ((1 << KIND_BITS) - 1);
                match item >> KIND_BITS {
                    KIND_BOX => self.hit_box(k, op, dp, &inv, best),
                    KIND_CYL => self.hit_cylinder(k, op, dp, best),
                    _ => self.hit_crown(k, op, dp, key, best),
                }
            }
            let t_exit = tx.min(ty);
            if t_exit >= best.t || t_exit >= t_top {
                return;
            }
            if tx < ty {
                ix += sx;
                if ix < 0 || ix >= g.nx {
                    return;
                }
                tx += dtx;
            } else {
                iy += sy;
                if iy < 0 || iy >= g.ny {
                    return;
                }
                ty += dty;
            }
        }
    }

    #[inline]
    fn hit_box(&self, k: u32, o: &[f64; 3], d: &[f64; 3], inv: &[f64; 3], best: &mut Best) {
        let b = &self.boxes[k as usize];
        let mut t_near = f64::NEG_INFINITY;
        let mut t_far = f64::INFINITY;
        let mut axis = 0usize;
        for a in 0..3 {
            if d[a].abs() < 1e-15 {
                if o[a] < b.min[a] || o[a] > b.max[a] {
                    return;
                }
                continue;
            }
            let t1 = (b.min[a] - o[a]) * inv[a];
            let t2 = (b.max[a] - o[a]) * inv[a];
            let (tn, tf) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
            if tn > t_near {
                t_near = tn;
                axis = a;
            }
            t_far = t_far.min(tf);
            if t_near > t_far {
                return;
            }
        }
        if t_near > T_EPS && t_near < best.t {
            // Entering through the min face when moving in +axis, else the max face.
            let face = (axis * 2) as u8 + u8::from(d[axis] < 0.0);
            *best = Best { t: t_near, what: HitRef::Box(k, face) };
        }
    }

    #[inline]
    fn hit_cylinder(&self, k: u32, o: &[f64; 3], d: &[f64; 3], best: &mut Best) {
        let c = &self.cyls[k as usize];
        let f = [o[0] - c.c[0], o[1] - c.c[1]];
        let a = d[0] * d[0] + d[1] * d[1];
        let cc = f[0] * f[0] + f[1] * f[1] - c.r * c.r;
        if cc < 0.0 {
            return; // origin inside the footprint: cannot happen for a scanner outside objects
        }
        if a > 1e-18 {
            let b = f[0] * d[0] + f[1] * d[1];
            let disc = b * b - a * cc;
            if disc >= 0.0 {
                let t = (-b - disc.sqrt()) / a;
                if t > T_EPS && t < best.t {
                    let z = o[2] + t * d[2];
                    if z >= c.z0 && z <= c.z1 {
                        let n = [(f[0] + t * d[0]) / c.r, (f[1] + t * d[1]) / c.r];
                        *best = Best { t, what: HitRef::CylSide(k, n) };
                        return;
                    }
                }
            }
        }
        if d[2] < 0.0 && o[2] > c.z1 {
            let t = (c.z1 - o[2]) / d[2];
            if t > T_EPS && t < best.t {
                let x = f[0] + t * d[0];
                let y = f[1] + t * d[1];
                if x * x + y * y <= c.r * c.r {
                    *best = Best { t, what: HitRef::CylCap(k) };
                }
            }
        }
    }

    /// A crown is a cloud of leaves: along the ray's chord through the sphere, the first leaf lies
    /// at an exponentially distributed depth (mean free path); beyond the chord the ray passes.
    #[inline]
    fn hit_crown(&self, k: u32, o: &[f64; 3], d: &[f64; 3], key: u64, best: &mut Best) {
        let c = &self.crowns[k as usize];
        let f = [o[0] - c.c[0], o[1] - c.c[1], o[2] - c.c[2]];
        let a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let b = f[0] * d[0] + f[1] * d[1] + f[2] * d[2];
        let cc = f[0] * f[0] + f[1] * f[1] + f[2] * f[2] - c.r * c.r;
        let disc = b * b - a * cc;
        if disc <= 0.0 {
            return;
        }
        let sq = disc.sqrt();
        let t_out = (-b + sq) / a;
        let t_in = ((-b - sq) / a).max(0.0);
        if t_out <= T_EPS || t_in >= best.t {
            return;
        }
        let depth = -self.mean_free_path * rng::unit(rng::hash2(key, c.id as u64)).ln();
        let t = t_in + depth;
        if t < t_out && t < best.t && t > T_EPS {
            *best = Best { t, what: HitRef::Crown(k) };
        }
    }
}

mod corners;
pub use corners::FacadeCorner;

#[cfg(test)]
mod tests;
