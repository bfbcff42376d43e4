//! Tile keys: square tiles of `tile_size_m` in absolute projected coordinates (paper §6.2). The
//! same key names a tile in memory, in chunk files and in object-store keys (`{tx}_{ty}`).

use crate::geom::floor;
use serde::{Deserialize, Serialize};
use std::fmt;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TileKey {
    pub tx: i32,
    pub ty: i32,
}

impl TileKey {
    pub fn of(x: f64, y: f64, tile_size_m: f64) -> Self {
        Self { tx: floor(x / tile_size_m) as i32, ty: floor(y / tile_size_m) as i32 }
    }

    /// South-west corner in absolute coordinates.
    pub fn origin(&self, tile_size_m: f64) -> (f64, f64) {
        (self.tx as f64 * tile_size_m, self.ty as f64 * tile_size_m)
    }

    /// The tiles a point at (x, y) belongs to: its own, plus each neighbour whose border lies
    /// within `overlap_m` (up to 4 tiles at a corner). The own tile comes first.
    pub fn with_overlap(x: f64, y: f64, tile_size_m: f64, overlap_m: f64) -> impl Iterator<Item = TileKey> {
        let home = Self::of(x, y, tile_size_m);
        let (x0, y0) = home.origin(tile_size_m);
        let dx = if x - x0 < overlap_m {
            -1
        } else if x0 + tile_size_m - x <= overlap_m {
            1
        } else {
            0
        };
        let dy = if y - y0 < overlap_m {
            -1
        } else if y0 + tile_size_m - y <= overlap_m {
            1
        } else {
            0
        };
        let candidates = [(0, 0), (dx, 0), (0, dy), (dx, dy)];
        candidates.into_iter().enumerate().filter_map(move |(k, (ox, oy))| {
            let keep = match k {
                0 => true,
                1 => ox != 0,
                2 => oy != 0,
                _ => ox != 0 && oy != 0,
            };
            keep.then_some(TileKey { tx: home.tx + ox, ty: home.ty + oy })
        })
    }
}

impl fmt::Display for TileKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}_{}", self.tx, self.ty)
    }
}

impl std::str::FromStr for TileKey {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (a, b) = s.split_once('_').ok_or_else(|| format!("tile key {s:?} is not of the form TX_TY"))?;
        let parse = |v: &str| v.parse::<i32>().map_err(|_| format!("tile key {s:?} is not of the form TX_TY"));
        Ok(Self { tx: parse(a)?, ty: parse(b)? })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_overlap() {
        let k = TileKey::of(549_800.1, 5_803_400.2, 15.0);
        assert_eq!(k, TileKey { tx: 36653, ty: 386893 });
        assert_eq!(k.to_string().parse::<TileKey>().unwrap(), k);
        let inner: Vec<_> = TileKey::with_overlap(7.0, 7.0, 15.0, 0.3).collect();
        assert_eq!(inner, vec![TileKey { tx: 0, ty: 0 }]);
        let corner: Vec<_> = TileKey::with_overlap(14.9, 0.1, 15.0, 0.3).collect();
        assert_eq!(
            corner,
            vec![
                TileKey { tx: 0, ty: 0 },
                TileKey { tx: 1, ty: 0 },
                TileKey { tx: 0, ty: -1 },
                TileKey { tx: 1, ty: -1 }
            ]
        );
        let neg = TileKey::of(-0.1, -15.0, 15.0);
        assert_eq!(neg, TileKey { tx: -1, ty: -1 });
    }
}
