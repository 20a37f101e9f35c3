//! The products: one image per name and slot, the index of slots by set, the dark mean.

use super::metadata::index_chunk;
use super::plane::Plane;
use super::*;

/// Stores `plane` as chunk `[slot, 0, 0]` of `a`, in `a`'s data type. A uint8 plane goes into
/// a float32 array unchanged in value (a run written before `flags` was an integer array and
/// resumed now); a float32 plane is never narrowed into an integer array.
fn store_plane(
    a: &Array<DurableStore>,
    name: &str,
    slot: u64,
    plane: Plane<'_>,
) -> Result<(), String> {
    let at = [slot, 0, 0];
    let float = a.data_type() == &data_type::float32();
    let stored = match plane {
        Plane::U8(v) if float => {
            let wide: Vec<f32> = v.iter().map(|&b| f32::from(b)).collect();
            a.store_chunk_opt(&at, wide.as_slice(), &codec_options())
        }
        Plane::U8(v) if a.data_type() == &data_type::uint8() => {
            a.store_chunk_opt(&at, v, &codec_options())
        }
        Plane::F32(v) if float => a.store_chunk_opt(&at, v, &codec_options()),
        _ => {
            return Err(format!(
                "product {name:?} is stored as {}; a {} image cannot be written into it",
                a.data_type(),
                match plane {
                    Plane::F32(_) => "float32",
                    Plane::U8(_) => "uint8",
                }
            ))
        }
    };
    stored.map_err(|e| e.to_string())
}

impl RunStore {
    pub(super) fn load_products(&self) -> Result<ProductsState, StoreError> {
        let (_, sets) = self.read_whole::<i64>(PRODUCT_SET)?;
        let (shape, flat) = self.read_whole::<f64>(PRODUCT_ANGLES)?;
        let k = shape.get(1).copied().unwrap_or(0) as usize;
        let angles: Vec<Vec<f64>> = if k == 0 {
            vec![Vec::new(); sets.len()]
        } else {
            flat.chunks(k)
                .map(|row| row.iter().copied().filter(|a| !a.is_nan()).collect())
                .collect()
        };
        // `products/set` is written last ([`Self::write_product_index`]): a process that
        // stopped between the two leaves `angles_deg` a row ahead; the set's products are
        // written again when it is processed again.
        let mut angles = angles;
        angles.resize(sets.len(), Vec::new());
        let names = self.product_names()?;
        let mut arrays = HashMap::new();
        let mut slots = sets.len() as u64;
        for name in &names {
            let node = format!("{PRODUCTS}/{name}");
            let a = Array::open(self.store.clone(), &node)
                .map_err(zarr_err(self.node(&node), "opening"))?;
            slots = slots.max(a.shape().first().copied().unwrap_or(0));
            arrays.insert(name.clone(), a);
        }
        Ok(ProductsState {
            slots,
            sets,
            angles,
            arrays,
            names,
        })
    }

    /// Rewrites `products/angles_deg`, then `products/set`: a slot counts for readers once
    /// its set is in `products/set`, which is written after the slot's images and angles.
    pub(super) fn write_product_index(
        &self,
        sets: &[i64],
        angles: &[Vec<f64>],
    ) -> Result<(), StoreError> {
        let m = sets.len() as u64;
        let k = angles.iter().map(Vec::len).max().unwrap_or(0);
        let mut flat = Vec::with_capacity(sets.len() * k);
        for row in angles {
            flat.extend_from_slice(row);
            flat.extend(std::iter::repeat_n(f64::NAN, k - row.len()));
        }
        self.write_whole(
            PRODUCT_ANGLES,
            vec![m, k as u64],
            index_chunk(2),
            &["slot", "channel"],
            data_type::float64(),
            ZARR_NAN_F64,
            &flat,
        )?;
        self.write_whole(
            PRODUCT_SET,
            vec![m],
            index_chunk(1),
            &["slot"],
            data_type::int64(),
            -1i64,
            sets,
        )
    }

    /// Stores the products of angle `set`: one `[H, W]` image per `(name, values)`, and the
    /// set's analyzer angles. Products are keyed by set: the set's slot (the index in the
    /// products arrays) is the one already holding it (written again, e.g. by a process that
    /// crashed before its journal recorded the set), else a new slot at the end. Product
    /// arrays are created on first use; every product array grows to the same number of
    /// slots. Returns the slot.
    ///
    /// The files are written and synced first and renamed into place together at the end,
    /// so a reader (or a crash) finds every product array and the index at one number of
    /// slots, the old or the new.
    pub fn write_products(
        &self,
        set: u64,
        angles_deg: &[f64],
        images: &[(&str, Plane<'_>)],
    ) -> Result<u64, StoreError> {
        // The planes this store keeps, at their precision ([`Storage::prepare`]).
        let kept = self.storage.prepare(images);
        let images: Vec<(&str, Plane<'_>)> = kept.iter().map(|(n, k)| (*n, k.plane())).collect();
        self.store.begin_batch();
        let written = self.write_products_files(set, angles_deg, &images);
        self.store
            .commit_batch(written.is_ok())
            .map_err(io_err(&self.path, "renaming the products into place"))?;
        written
    }

    fn write_products_files(
        &self,
        set: u64,
        angles_deg: &[f64],
        images: &[(&str, Plane<'_>)],
    ) -> Result<u64, StoreError> {
        let mut seen = BTreeSet::new();
        for (name, plane) in images {
            check_product_name(name)?;
            if !seen.insert(*name) {
                return Err(StoreError::Product {
                    name: (*name).to_string(),
                    message: "given twice".into(),
                });
            }
            self.check_image(|| format!("product {name:?}"), plane.len())?;
        }
        let set_i64 = i64::try_from(set).map_err(|_| StoreError::Product {
            name: "set".into(),
            message: format!("set number {set} is larger than the int64 array can hold"),
        })?;
        let mut guard = lock(&self.products);
        if guard.is_none() {
            *guard = Some(self.load_products()?);
        }
        let Some(state) = guard.as_mut() else {
            return Err(StoreError::Layout {
                path: self.node(PRODUCTS),
                message: "products state not loaded".into(),
            });
        };
        let slot_usize = state
            .sets
            .iter()
            .position(|&s| s == set_i64)
            .unwrap_or(state.sets.len());
        let slot = slot_usize as u64;
        let slots = state.slots.max(slot + 1);
        // Grow existing arrays, create new ones.
        for name in state.names.clone() {
            if let Some(a) = state.arrays.get_mut(&name) {
                if a.shape().first().copied().unwrap_or(0) < slots {
                    let node = format!("{PRODUCTS}/{name}");
                    let grown = product_array(
                        &self.store,
                        &node,
                        slots,
                        (self.width, self.height),
                        &self.storage,
                    )
                    .map_err(zarr_err(self.node(&node), "growing"))?;
                    grown
                        .store_metadata()
                        .map_err(zarr_err(self.node(&node), "writing the array metadata"))?;
                    *a = grown;
                }
            }
        }
        let mut new_names = false;
        for (name, _) in images {
            if !state.arrays.contains_key(*name) {
                let node = format!("{PRODUCTS}/{name}");
                let a = product_array(
                    &self.store,
                    &node,
                    slots,
                    (self.width, self.height),
                    &self.storage,
                )
                .map_err(zarr_err(self.node(&node), "creating the array"))?;
                a.store_metadata()
                    .map_err(zarr_err(self.node(&node), "writing the array metadata"))?;
                state.arrays.insert((*name).to_string(), a);
                state.names.push((*name).to_string());
                new_names = true;
            }
        }
        state.slots = slots;
        if new_names {
            let names = state.names.iter().cloned().map(Value::String).collect();
            self.update_group_attribute(PRODUCTS, "names", Value::Array(names))?;
        }
        for (name, plane) in images {
            if let Some(a) = state.arrays.get(*name) {
                store_plane(a, name, slot, *plane).map_err(|message| StoreError::Product {
                    name: (*name).to_string(),
                    message: format!("{}: {message}", self.chunk_path(a, &[slot, 0, 0]).display()),
                })?;
            }
        }
        let m = slots as usize;
        state.sets.resize(m, -1);
        state.angles.resize(m, Vec::new());
        state.sets[slot_usize] = set_i64;
        state.angles[slot_usize] = angles_deg.to_vec();
        self.write_product_index(&state.sets, &state.angles)?;
        Ok(slot)
    }

    /// Records which dark set `set`'s products subtract: in words (the `dark` attribute of
    /// `products/`, an object by set number) and for a reader to recompute (`dark_source`:
    /// `{"level_dn": L}` for a scalar level, `{"dark_frames": N, "exposure_us": T}` for the
    /// mean of the run's first N dark frames at exposure T).
    pub fn set_product_dark(
        &self,
        set: u64,
        description: &str,
        source: Value,
    ) -> Result<(), StoreError> {
        let key = set.to_string();
        self.insert_into_attribute(PRODUCTS, "dark", &key, json!(description))?;
        self.insert_into_attribute(PRODUCTS, "dark_source", &key, source)
    }

    /// Records the share of set `set`'s pixels where a frame saturated (the
    /// `saturated_fraction` attribute of `products/`, an object by set number).
    pub fn set_product_saturation(&self, set: u64, fraction: f64) -> Result<(), StoreError> {
        self.insert_into_attribute(
            PRODUCTS,
            "saturated_fraction",
            &set.to_string(),
            json!(fraction),
        )
    }

    /// Every set's saturated share of pixels ([`RunStore::set_product_saturation`]), by set.
    pub fn product_saturation(&self) -> Result<std::collections::BTreeMap<u64, f64>, StoreError> {
        if !self.node_exists(PRODUCTS) {
            return Ok(Default::default());
        }
        let attrs = self.group_attributes(PRODUCTS)?;
        Ok(attrs
            .get("saturated_fraction")
            .and_then(Value::as_object)
            .into_iter()
            .flatten()
            .filter_map(|(k, v)| Some((k.parse().ok()?, v.as_f64()?)))
            .collect())
    }

    /// Reads product `name` of `slot`, as float32 whatever its stored type (the uint8 `flags`
    /// convert exactly). S1 and S2, when the store keeps only the essential planes, are
    /// derived from S0, DoLP and AoP ([`super::storage::derive`]).
    pub fn read_product(&self, name: &str, slot: u64) -> Result<Vec<f32>, StoreError> {
        check_product_name(name)?;
        let node = format!("{PRODUCTS}/{name}");
        let derivable = super::storage::DERIVED.contains(&name)
            && ["s0", "dolp", "aop_rad"]
                .iter()
                .all(|n| self.node_exists(&format!("{PRODUCTS}/{n}")));
        if !self.node_exists(&node) && derivable {
            let [s0, dolp, aop] = ["s0", "dolp", "aop_rad"].map(|n| self.read_product(n, slot));
            if let Some(v) = super::storage::derive(name, &s0?, &dolp?, &aop?) {
                return Ok(v);
            }
        }
        if !self.node_exists(&node) {
            return Err(StoreError::Product {
                name: name.into(),
                message: format!("not in the store (products: {:?})", self.product_names()?),
            });
        }
        let a = Array::open(self.store.clone(), &node)
            .map_err(zarr_err(self.node(&node), "opening"))?;
        let slots = a.shape().first().copied().unwrap_or(0);
        if slot >= slots {
            return Err(StoreError::Product {
                name: name.into(),
                message: format!("slot {slot} is past the {slots} slots stored"),
            });
        }
        let at = [slot, 0, 0];
        let failed = zarr_err(
            self.chunk_path(&a, &at).display().to_string(),
            "reading product chunk",
        );
        let values = if a.data_type() == &data_type::uint8() {
            a.retrieve_chunk_if_exists_opt::<Vec<u8>>(&at, &codec_options())
                .map_err(failed)?
                .map(|v| v.into_iter().map(f32::from).collect())
        } else {
            a.retrieve_chunk_if_exists_opt::<Vec<f32>>(&at, &codec_options())
                .map_err(failed)?
        };
        values.ok_or_else(|| StoreError::MissingChunk {
            path: self.chunk_path(&a, &at),
            what: format!("product {name:?} of slot {slot}"),
        })
    }

    /// The product names written so far (the `names` attribute of `products/`).
    pub fn product_names(&self) -> Result<Vec<String>, StoreError> {
        let attrs = self.group_attributes(PRODUCTS)?;
        let names = attrs
            .get("names")
            .and_then(Value::as_array)
            .map(|a| {
                a.iter()
                    .filter_map(|v| v.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default();
        Ok(names)
    }

    /// The product slots: the set and angles of each.
    pub fn product_slots(&self) -> Result<Vec<ProductSlot>, StoreError> {
        let state = self.load_products()?;
        Ok(state
            .sets
            .iter()
            .zip(state.angles)
            .enumerate()
            .map(|(slot, (&set, angles_deg))| ProductSlot {
                slot: slot as u64,
                set: u64::try_from(set).ok(),
                angles_deg,
            })
            .collect())
    }

    /// Writes the mean dark frame (`darks/mean`, float32 `[H, W]`), replacing any earlier one.
    pub fn write_dark_mean(&self, mean: &[f32]) -> Result<(), StoreError> {
        self.check_image(|| "dark mean".into(), mean.len())?;
        self.write_whole(
            DARK_MEAN,
            vec![u64::from(self.height), u64::from(self.width)],
            vec![u64::from(self.height), u64::from(self.width)],
            &["y", "x"],
            data_type::float32(),
            ZARR_NAN_F32,
            mean,
        )
    }

    /// The mean dark frame, if one was written.
    pub fn read_dark_mean(&self) -> Result<Option<Vec<f32>>, StoreError> {
        if !self.node_exists(DARK_MEAN) {
            return Ok(None);
        }
        let (_, v) = self.read_whole::<f32>(DARK_MEAN)?;
        Ok(Some(v))
    }
}

fn check_product_name(name: &str) -> Result<(), StoreError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        && !name.starts_with('-')
        && !PRODUCT_RESERVED.contains(&name);
    if ok {
        Ok(())
    } else {
        Err(StoreError::Product {
            name: name.to_string(),
            message: format!(
                "a product name is 1 to 64 of [A-Za-z0-9_-] (not starting with '-') and not \
                 one of {PRODUCT_RESERVED:?}"
            ),
        })
    }
}
