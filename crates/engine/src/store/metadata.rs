//! The per-frame metadata arrays and the small arrays written whole in fixed-size chunks.

use super::*;

/// Rows per chunk of the small index arrays (the per-frame metadata, `products/set`,
/// `products/angles_deg`): fixed, so an array's chunks keep their size as it grows.
const INDEX_ROWS_PER_CHUNK: u64 = 4096;
/// Columns per chunk of the two-dimensional index array `products/angles_deg`.
const INDEX_COLUMNS_PER_CHUNK: u64 = 32;

/// The chunk shape of a small index array of `rank` dimensions.
pub(super) fn index_chunk(rank: usize) -> Vec<u64> {
    let mut chunk = vec![INDEX_COLUMNS_PER_CHUNK; rank];
    if let Some(rows) = chunk.first_mut() {
        *rows = INDEX_ROWS_PER_CHUNK;
    }
    chunk
}

/// The chunks of a regular grid covering `shape`: each chunk's grid indices and, for each of
/// its elements in C order, the element's index in the whole array in C order (`None`
/// outside the shape, in an edge chunk's padding).
pub(super) fn chunks_of(shape: &[u64], chunk: &[u64]) -> Vec<(Vec<u64>, Vec<Option<usize>>)> {
    let grid: Vec<u64> = shape
        .iter()
        .zip(chunk)
        .map(|(&s, &c)| s.div_ceil(c.max(1)))
        .collect();
    let count: u64 = grid.iter().product();
    let per_chunk: u64 = chunk.iter().product();
    let mut out = Vec::with_capacity(count as usize);
    for flat_chunk in 0..count {
        let indices = unravel(flat_chunk, &grid);
        let elements = (0..per_chunk)
            .map(|flat_element| {
                let within = unravel(flat_element, chunk);
                let mut index = 0u64;
                for d in 0..shape.len() {
                    let at = indices[d] * chunk[d] + within[d];
                    if at >= shape[d] {
                        return None;
                    }
                    index = index * shape[d] + at;
                }
                Some(index as usize)
            })
            .collect();
        out.push((indices, elements));
    }
    out
}

/// The C-order multi-index of `flat` in an array of `shape`.
fn unravel(mut flat: u64, shape: &[u64]) -> Vec<u64> {
    let mut index = vec![0u64; shape.len()];
    for d in (0..shape.len()).rev() {
        let n = shape[d].max(1);
        index[d] = flat % n;
        flat /= n;
    }
    index
}

/// The per-frame arrays of the store, one value per frame ([`RunStore::frame_columns`]).
#[derive(Default)]
struct FrameColumns {
    kind: Vec<u8>,
    step: Vec<u64>,
    set: Vec<i64>,
    commanded: Vec<f64>,
    measured: Vec<f64>,
    start: Vec<f64>,
    end: Vec<f64>,
    source: Vec<u8>,
    angle_sigma: Vec<f64>,
    exposure: Vec<f64>,
    gain: Vec<f64>,
    host_time: Vec<i64>,
    device_time: Vec<i64>,
    frame_id: Vec<u64>,
    zenith: Vec<f64>,
    azimuth: Vec<f64>,
    hash: Vec<u64>,
    labels: Vec<Value>,
}

impl RunStore {
    /// Rewrites the per-frame metadata arrays (and the `labels` attribute of `frames/`) from
    /// `records`, which must be sorted by index and cover `0..N` without gaps, and resizes
    /// `frames/pixels` to N frames: the journal is the truth, the store mirrors it.
    ///
    /// `status` holds the frames that do not count, by index, with their `frames/status` code
    /// ([`crate::journal::frame_status`]); every other frame counts (`frames/accepted` 1).
    ///
    /// Each call rewrites every array (O(N), about 30 small synced files): call it at set
    /// boundaries and at the end, not for every frame. The files are written and synced
    /// first and renamed into place together at the end, so a reader (or a crash) finds
    /// every per-frame array and frames/pixels at one length, the old or the new.
    pub fn write_frame_metadata(
        &self,
        records: &[FrameRecord],
        status: &std::collections::BTreeMap<u64, u8>,
    ) -> Result<(), StoreError> {
        self.store.begin_batch();
        let written = self.write_frame_metadata_files(records, status);
        self.store
            .commit_batch(written.is_ok())
            .map_err(io_err(&self.path, "renaming the frame metadata into place"))?;
        written
    }

    /// The per-frame arrays' values of `records` (sorted by index, without gaps, of the
    /// store's frame size).
    fn frame_columns(&self, records: &[FrameRecord]) -> Result<FrameColumns, StoreError> {
        let n = records.len();
        let mut c = FrameColumns::default();
        for (i, r) in records.iter().enumerate() {
            let bad = |field: &str, value: String, message: String| StoreError::Metadata {
                field: format!("records[{i}].{field}"),
                value,
                message,
            };
            if r.index != i as u64 {
                return Err(bad(
                    "index",
                    r.index.to_string(),
                    format!(
                        "records must be sorted by index and cover 0..{n} without gaps \
                         (expected {i})"
                    ),
                ));
            }
            if (r.width, r.height) != (self.width, self.height) {
                return Err(bad(
                    "width x height",
                    format!("{}x{}", r.width, r.height),
                    format!("the store holds {}x{} frames", self.width, self.height),
                ));
            }
            let to_i64 = |field: &str, v: u64| {
                i64::try_from(v).map_err(|_| {
                    bad(
                        field,
                        v.to_string(),
                        "larger than the int64 array can hold".into(),
                    )
                })
            };
            c.kind.push(r.kind.code());
            c.step.push(r.step);
            c.set.push(match r.set {
                Some(s) => to_i64("set", s)?,
                None => -1,
            });
            c.commanded.push(r.commanded_angle_deg);
            c.measured.push(r.measured_angle_deg);
            c.start.push(r.angle_start_deg);
            c.end.push(r.angle_end_deg);
            c.source.push(r.angle_source.code());
            c.angle_sigma.push(r.angle_sigma_deg);
            c.exposure.push(r.exposure_us);
            c.gain.push(r.gain);
            c.host_time.push(r.host_time_unix_ns);
            c.device_time.push(match r.device_timestamp_ns {
                Some(t) => to_i64("device_timestamp_ns", t)?,
                None => -1,
            });
            c.frame_id.push(r.frame_id);
            c.zenith.push(r.sun_zenith_deg.unwrap_or(f64::NAN));
            c.azimuth.push(r.sun_azimuth_deg.unwrap_or(f64::NAN));
            c.hash.push(r.hash);
            c.labels.push(Value::String(r.label.clone()));
        }
        Ok(c)
    }

    fn write_frame_metadata_files(
        &self,
        records: &[FrameRecord],
        status: &std::collections::BTreeMap<u64, u8>,
    ) -> Result<(), StoreError> {
        let c = self.frame_columns(records)?;
        let n = records.len();
        let n = n as u64;
        let dims = ["frame"];
        self.write_whole(
            "/frames/kind",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint8(),
            0u8,
            &c.kind,
        )?;
        self.write_whole(
            "/frames/step",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &c.step,
        )?;
        self.write_whole(
            "/frames/set",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            -1i64,
            &c.set,
        )?;
        for (name, values) in [
            ("commanded_angle_deg", &c.commanded),
            ("measured_angle_deg", &c.measured),
            ("angle_start_deg", &c.start),
            ("angle_end_deg", &c.end),
            ("angle_sigma_deg", &c.angle_sigma),
            ("exposure_us", &c.exposure),
            ("gain", &c.gain),
            ("sun_zenith_deg", &c.zenith),
            ("sun_azimuth_deg", &c.azimuth),
        ] {
            self.write_whole(
                &format!("{FRAMES}/{name}"),
                vec![n],
                index_chunk(1),
                &dims,
                data_type::float64(),
                ZARR_NAN_F64,
                values,
            )?;
        }
        self.write_whole(
            "/frames/angle_source",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint8(),
            0u8,
            &c.source,
        )?;
        self.write_whole(
            "/frames/host_time_unix_ns",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            0i64,
            &c.host_time,
        )?;
        self.write_whole(
            "/frames/device_timestamp_ns",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            -1i64,
            &c.device_time,
        )?;
        self.write_whole(
            "/frames/frame_id",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &c.frame_id,
        )?;
        self.write_whole(
            "/frames/hash",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &c.hash,
        )?;
        let codes: Vec<u8> = (0..n)
            .map(|i| status.get(&i).copied().unwrap_or(0))
            .collect();
        let accepted: Vec<u8> = codes.iter().map(|&c| u8::from(c == 0)).collect();
        for (node, values) in [("/frames/status", &codes), ("/frames/accepted", &accepted)] {
            self.write_whole(
                node,
                vec![n],
                index_chunk(1),
                &dims,
                data_type::uint8(),
                0u8,
                values,
            )?;
        }
        self.update_group_attribute(FRAMES, "labels", Value::Array(c.labels))?;

        // frames/pixels last: its shape on disk is what readers take as the frame count.
        let mut array = lock(&self.pixels);
        let resized = pixels_array(&self.store, n, (self.width, self.height), &self.storage)
            .map_err(zarr_err(self.node(PIXELS), "resizing"))?;
        resized
            .store_metadata()
            .map_err(zarr_err(self.node(PIXELS), "writing the array metadata"))?;
        *array = resized;
        self.pixels_ahead
            .store(false, std::sync::atomic::Ordering::SeqCst);
        Ok(())
    }

    /// Writes a small array whole (the per-frame metadata, the products' index, the dark
    /// mean). The chunk shape is fixed by the array's kind ([`index_chunk`], or one chunk for
    /// an image), never by its current length: chunks are stored before the metadata when the
    /// array grows and after it when it shrinks, so a crash between the two leaves metadata
    /// whose every chunk decodes, and readers see the older or the newer values, never a
    /// chunk of the wrong size.
    #[allow(clippy::too_many_arguments)] // one call shape for every small array
    pub(super) fn write_whole<T: Element + Copy + Into<ArrayBuilderFillValue>>(
        &self,
        node: &str,
        shape: Vec<u64>,
        chunk: Vec<u64>,
        dims: &[&str],
        data_type: DataType,
        fill: T,
        data: &[T],
    ) -> Result<(), StoreError> {
        let shrinks = Array::open(self.store.clone(), node)
            .ok()
            .and_then(|old| old.shape().first().copied())
            .is_some_and(|old_len| old_len > shape.first().copied().unwrap_or(0));
        let array = schema::array(
            self.store.clone(),
            node,
            shape.clone(),
            chunk.clone(),
            data_type,
            fill,
            dims,
            self.storage.compressed(),
        )
        .map_err(zarr_err(self.node(node), "creating the array"))?;
        let store_metadata = || {
            array
                .store_metadata()
                .map_err(zarr_err(self.node(node), "writing the array metadata"))
        };
        if shrinks {
            store_metadata()?;
        }
        for (indices, elements) in chunks_of(&shape, &chunk) {
            let values: Vec<T> = elements
                .iter()
                .map(|e| e.map_or(fill, |i| data[i]))
                .collect();
            array
                .store_chunk_opt(&indices, values, &codec_options())
                .map_err(zarr_err(self.node(node), "writing the array"))?;
        }
        if !shrinks {
            store_metadata()?;
        }
        Ok(())
    }

    /// Reads a small array written by [`Self::write_whole`]: (shape, values in C order). Every
    /// chunk the shape covers must exist and pass its checksum.
    pub(super) fn read_whole<T: ElementOwned + Copy>(
        &self,
        node: &str,
    ) -> Result<(Vec<u64>, Vec<T>), StoreError> {
        let array =
            Array::open(self.store.clone(), node).map_err(zarr_err(self.node(node), "opening"))?;
        let shape = array.shape().to_vec();
        if shape.contains(&0) {
            return Ok((shape, Vec::new()));
        }
        let origin = vec![0u64; shape.len()];
        let chunk: Vec<u64> = array
            .chunk_shape(&origin)
            .map_err(zarr_err(self.node(node), "reading the chunk grid"))?
            .iter()
            .map(|c| c.get())
            .collect();
        let total = shape.iter().product::<u64>() as usize;
        let mut values: Vec<Option<T>> = vec![None; total];
        for (indices, elements) in chunks_of(&shape, &chunk) {
            let stored = array
                .retrieve_chunk_if_exists_opt::<Vec<T>>(&indices, &codec_options())
                .map_err(zarr_err(self.node(node), "reading"))?
                .ok_or_else(|| StoreError::MissingChunk {
                    path: self.chunk_path(&array, &indices),
                    what: format!("the values of {}", node.trim_start_matches('/')),
                })?;
            for (value, element) in stored.into_iter().zip(elements) {
                if let Some(i) = element {
                    values[i] = Some(value);
                }
            }
        }
        let values = values
            .into_iter()
            .collect::<Option<Vec<T>>>()
            .ok_or_else(|| StoreError::Layout {
                path: self.node(node),
                message: "its chunks do not cover its shape".into(),
            })?;
        Ok((shape, values))
    }

    /// Each frame's `frames/status` code (0: it counts); empty for a store written before
    /// frames recorded it.
    pub fn read_frame_status(&self) -> Result<Vec<u8>, StoreError> {
        if !self.node_exists(&format!("{FRAMES}/status")) {
            return Ok(Vec::new());
        }
        Ok(self.read_whole::<u8>(&format!("{FRAMES}/status"))?.1)
    }

    /// Reads the per-frame metadata back as frame records (labels from the `labels`
    /// attribute of `frames/`; width and height from the store).
    pub fn read_frame_metadata(&self) -> Result<Vec<FrameRecord>, StoreError> {
        fn column<T: ElementOwned + Copy>(
            s: &RunStore,
            name: &str,
            n: &mut Option<usize>,
        ) -> Result<Vec<T>, StoreError> {
            let (_, v) = s.read_whole::<T>(&format!("{FRAMES}/{name}"))?;
            match n {
                None => *n = Some(v.len()),
                Some(n) if *n != v.len() => {
                    return Err(StoreError::Metadata {
                        field: format!("frames/{name}"),
                        value: format!("{} values", v.len()),
                        message: format!("the other per-frame arrays hold {n}"),
                    })
                }
                Some(_) => {}
            }
            Ok(v)
        }
        let mut n = None;
        let kind: Vec<u8> = column(self, "kind", &mut n)?;
        let step: Vec<u64> = column(self, "step", &mut n)?;
        let set: Vec<i64> = column(self, "set", &mut n)?;
        let commanded: Vec<f64> = column(self, "commanded_angle_deg", &mut n)?;
        let measured: Vec<f64> = column(self, "measured_angle_deg", &mut n)?;
        let exposure: Vec<f64> = column(self, "exposure_us", &mut n)?;
        let gain: Vec<f64> = column(self, "gain", &mut n)?;
        let host_time: Vec<i64> = column(self, "host_time_unix_ns", &mut n)?;
        let device_time: Vec<i64> = column(self, "device_timestamp_ns", &mut n)?;
        let frame_id: Vec<u64> = column(self, "frame_id", &mut n)?;
        let zenith: Vec<f64> = column(self, "sun_zenith_deg", &mut n)?;
        let azimuth: Vec<f64> = column(self, "sun_azimuth_deg", &mut n)?;
        let hash: Vec<u64> = column(self, "hash", &mut n)?;
        // Runs written before frames recorded their span have no span arrays: their frames
        // are step-and-shoot frames, whose span is the settled reading.
        let span = if self.node_exists(&format!("{FRAMES}/angle_source")) {
            Some((
                column::<f64>(self, "angle_start_deg", &mut n)?,
                column::<f64>(self, "angle_end_deg", &mut n)?,
                column::<u8>(self, "angle_source", &mut n)?,
                column::<f64>(self, "angle_sigma_deg", &mut n)?,
            ))
        } else {
            None
        };
        let n = n.unwrap_or(0);
        let attrs = self.group_attributes(FRAMES)?;
        let labels = match attrs.get("labels") {
            Some(Value::Array(a)) if a.len() == n => a,
            other => {
                return Err(StoreError::Metadata {
                    field: "frames/ attribute \"labels\"".into(),
                    value: other.map_or("missing".into(), |v| {
                        let s = v.to_string();
                        s.chars().take(80).collect()
                    }),
                    message: format!("expected an array of {n} strings"),
                })
            }
        };
        let mut records = Vec::with_capacity(n);
        for i in 0..n {
            let kind = FrameKind::from_code(kind[i]).ok_or_else(|| StoreError::Metadata {
                field: format!("frames/kind[{i}]"),
                value: kind[i].to_string(),
                message: "expected 0 (light) or 1 (dark)".into(),
            })?;
            let label = labels[i]
                .as_str()
                .ok_or_else(|| StoreError::Metadata {
                    field: format!("frames/ attribute \"labels\"[{i}]"),
                    value: labels[i].to_string(),
                    message: "expected a string".into(),
                })?
                .to_string();
            let opt = |v: f64| if v.is_nan() { None } else { Some(v) };
            let (angle_start_deg, angle_end_deg, angle_source, angle_sigma_deg) = match &span {
                Some((a, b, c, d)) => (
                    a[i],
                    b[i],
                    AngleSource::from_code(c[i]).ok_or_else(|| StoreError::Metadata {
                        field: format!("frames/angle_source[{i}]"),
                        value: c[i].to_string(),
                        message: "expected 0 (settled), 1 (encoder trigger) or 2 (timestamps)"
                            .into(),
                    })?,
                    d[i],
                ),
                None => (measured[i], measured[i], AngleSource::Settled, f64::NAN),
            };
            records.push(FrameRecord {
                index: i as u64,
                step: step[i],
                kind,
                set: u64::try_from(set[i]).ok(),
                label,
                commanded_angle_deg: commanded[i],
                measured_angle_deg: measured[i],
                angle_start_deg,
                angle_end_deg,
                angle_source,
                angle_sigma_deg,
                exposure_us: exposure[i],
                gain: gain[i],
                host_time_unix_ns: host_time[i],
                device_timestamp_ns: u64::try_from(device_time[i]).ok(),
                frame_id: frame_id[i],
                sun_zenith_deg: opt(zenith[i]),
                sun_azimuth_deg: opt(azimuth[i]),
                width: self.width,
                height: self.height,
                hash: hash[i],
            });
        }
        Ok(records)
    }
}
