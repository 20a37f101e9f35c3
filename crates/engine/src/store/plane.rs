//! A product image as the store takes it: float32 planes and the uint8 bit mask `flags`.

/// One product image of a set, in its array's data type: the measured planes are float32,
/// the bit mask `flags` is uint8.
#[derive(Debug, Clone, Copy)]
pub enum Plane<'a> {
    /// A float32 image (Stokes, DoLP, AoP and their sigmas).
    F32(&'a [f32]),
    /// An unsigned 8-bit image (the bit mask `flags`).
    U8(&'a [u8]),
}

impl Plane<'_> {
    /// The number of pixels.
    pub fn len(&self) -> usize {
        match self {
            Plane::F32(v) => v.len(),
            Plane::U8(v) => v.len(),
        }
    }

    /// Whether the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl<'a> From<&'a Vec<f32>> for Plane<'a> {
    fn from(v: &'a Vec<f32>) -> Self {
        Plane::F32(v)
    }
}
