//! Errors of the products: each names the field, its value and what is allowed.

/// Errors of the products. Each names the field, its value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProductsError {
    /// Fewer than 3 analyzer rows.
    #[error(
        "rows: {count} analyzer rows given; at least 3 are needed (S0, S1, S2 are 3 unknowns)"
    )]
    TooFewRows {
        /// Rows given.
        count: usize,
    },
    /// An analyzer row with a non-finite entry.
    #[error("rows[{index}] = {row:?}: every entry must be finite")]
    NonFiniteRow {
        /// Row index.
        index: usize,
        /// The row.
        row: [f64; 3],
    },
    /// A non-finite analyzer angle.
    #[error("angles_rad[{index}] = {value}: must be finite")]
    NonFiniteAngle {
        /// Angle index.
        index: usize,
        /// The angle.
        value: f64,
    },
    /// The rows' largest entry is outside [`ROW_SCALE_RANGE`].
    #[error(
        "rows: largest |entry| = {value:e}, allowed [1e-3, 1e3] (DN per Stokes unit; 0.5 for \
         an ideal polarizer)"
    )]
    RowScale {
        /// The largest absolute entry.
        value: f64,
    },
    /// `A^T A` singular or ill-conditioned.
    #[error(
        "analyzer set singular or ill-conditioned: reciprocal condition number of A^T A = \
         {rcond:e}, allowed >= {min:e}; analyzer angles (deg, from the rows) = {angles_deg:?}: \
         at least 3 distinct angles modulo 180 deg are needed"
    )]
    Singular {
        /// The analyzer angle of each row, degrees in `[0, 180)`.
        angles_deg: Vec<f64>,
        /// Reciprocal condition number of `A^T A`.
        rcond: f64,
        /// The smallest accepted, [`MIN_RCOND`].
        min: f64,
    },
    /// The number of frames differs from the number of analyzer rows.
    #[error("frames: {frames} frames given, the set geometry has {rows} analyzer rows; they must be equal")]
    FrameCount {
        /// Frames given.
        frames: usize,
        /// Rows of the geometry.
        rows: usize,
    },
    /// A frame's length differs from `width * height`.
    #[error(
        "frames[{index}]: length {len}, expected width * height = {width} * {height} = {expected}"
    )]
    FrameLength {
        /// Frame index.
        index: usize,
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// `width * height` does not fit in `usize`.
    #[error("size {width} x {height}: width * height must fit in usize")]
    Size {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// A dark map's length differs from `width * height`.
    #[error("dark map: length {len}, expected width * height = {expected}")]
    DarkMapLength {
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
    },
    /// A non-finite scalar dark level.
    #[error("dark: scalar value {value}: must be finite")]
    NonFiniteDark {
        /// The value.
        value: f32,
    },
    /// A noise parameter out of range.
    #[error("noise.{field} = {value}: allowed {allowed}")]
    Noise {
        /// The field of [`NoiseModel`].
        field: &'static str,
        /// Its value.
        value: f64,
        /// The allowed range.
        allowed: &'static str,
    },
    /// A summary mask whose length differs from the pixel count.
    #[error("mask: length {len}, expected width * height = {expected} (one entry per pixel)")]
    MaskLength {
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
    },
    /// A worker thread panicked (a bug: the kernel has no panicking path).
    #[error("products: a worker thread panicked")]
    Worker,
}
