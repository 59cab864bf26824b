use serde::{Deserialize, Serialize};

/// A marker's identity: its (row, col) on the marker lattice of the LEFT view's reference frame.
///
/// Row grows with image y, col with image x, (0, 0) is top-left. Ordering is row-major, so sorting
/// indices gives the deterministic order used in every table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
pub struct GridIndex {
    /// Row, from the top.
    pub row: u16,
    /// Column, from the left.
    pub col: u16,
}

impl GridIndex {
    /// The index at `row`, `col`.
    pub const fn new(row: u16, col: u16) -> Self {
        Self { row, col }
    }
}

impl std::fmt::Display for GridIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "({}, {})", self.row, self.col)
    }
}

/// Size of a marker lattice (23 x 23 = 529 on the reference GelStereo sensor).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct GridShape {
    /// Number of marker rows.
    pub rows: u16,
    /// Number of marker columns.
    pub cols: u16,
}

impl GridShape {
    /// The reference GelStereo sensor's 23 x 23 lattice.
    pub const REFERENCE: GridShape = GridShape { rows: 23, cols: 23 };

    /// Number of markers on the lattice.
    pub fn count(&self) -> usize {
        usize::from(self.rows) * usize::from(self.cols)
    }

    /// Whether `index` lies on this lattice.
    pub fn contains(&self, index: GridIndex) -> bool {
        index.row < self.rows && index.col < self.cols
    }

    /// Row-major position of `index` in a dense array of [`count`](Self::count) entries.
    pub fn linear(&self, index: GridIndex) -> Option<usize> {
        self.contains(index)
            .then(|| usize::from(index.row) * usize::from(self.cols) + usize::from(index.col))
    }

    /// All indices, row-major.
    pub fn indices(&self) -> impl Iterator<Item = GridIndex> + use<> {
        let cols = self.cols;
        (0..self.rows).flat_map(move |row| (0..cols).map(move |col| GridIndex { row, col }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_index_is_row_major_and_rejects_outside() {
        let g = GridShape { rows: 3, cols: 4 };
        let all: Vec<_> = g.indices().collect();
        assert_eq!(all.len(), 12);
        for (i, idx) in all.iter().enumerate() {
            assert_eq!(g.linear(*idx), Some(i));
        }
        assert_eq!(g.linear(GridIndex::new(3, 0)), None);
        assert_eq!(g.linear(GridIndex::new(0, 4)), None);
        let mut sorted = all.clone();
        sorted.sort();
        assert_eq!(sorted, all, "Ord on GridIndex is row-major");
    }
}
