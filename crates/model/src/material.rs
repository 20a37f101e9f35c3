//! A small library of materials at 550 nm (refractive index, roughness, reflectance), loadable
//! from and savable to TOML. The built-in library is `data/materials.toml`; every entry carries
//! the source of its numbers in its `source` field.
//!
//! The model crate does no I/O: this module converts between TOML text and values; the CLI reads
//! and writes files.

use crate::error::ModelError;
use crate::fresnel::RefractiveIndex;
use crate::pbrdf::Surface;
use serde::{Deserialize, Serialize};

/// The built-in library's TOML text.
pub const BUILTIN_TOML: &str = include_str!("../data/materials.toml");

/// Which pBRDF model a material uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MaterialModel {
    /// Microfacet specular lobe plus Lambertian diffuse from the DHR (Meng (2012) Eqs. 3.4-3.18);
    /// needs `sigma` and `dhr`.
    Microfacet,
    /// Vegetation canopy (Eq. 3.19) plus an unpolarised diffuse term; needs `f00_diffuse`.
    Vegetation,
}

/// One material. The TOML table is flat; which optional fields are required depends on `model`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Unique name (lower case, used on the command line).
    pub name: String,
    /// Wavelength the constants refer to, nm.
    pub wavelength_nm: f64,
    /// Real part of the refractive index.
    pub n: f64,
    /// Extinction coefficient (0 for dielectrics).
    #[serde(default)]
    pub k: f64,
    /// The reflection model.
    pub model: MaterialModel,
    /// Facet-slope roughness `sigma = sigma_h / l` (Eq. 3.13); microfacet only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<f64>,
    /// Directional-hemispherical reflectance (Eq. 3.17); microfacet only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dhr: Option<f64>,
    /// Unpolarised diffuse BRDF `f00_d`, sr^-1; vegetation only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub f00_diffuse: Option<f64>,
    /// Where the numbers come from.
    pub source: String,
}

impl Material {
    /// Validates the parameters and builds the surface model. Errors name the material's field.
    pub fn surface(&self) -> Result<Surface, ModelError> {
        let index = RefractiveIndex::new(self.n, self.k)?;
        let missing = |field: &'static str| ModelError::Invalid {
            field,
            reason: format!("required when model = {:?}", self.model),
        };
        let extra = |field: &'static str| ModelError::Invalid {
            field,
            reason: format!("not used by model = {:?}; remove it", self.model),
        };
        match self.model {
            MaterialModel::Microfacet => {
                if self.f00_diffuse.is_some() {
                    return Err(extra("f00_diffuse"));
                }
                let sigma = self.sigma.ok_or_else(|| missing("sigma"))?;
                let dhr = self.dhr.ok_or_else(|| missing("dhr"))?;
                Surface::microfacet(index, sigma, dhr)
            }
            MaterialModel::Vegetation => {
                if self.sigma.is_some() {
                    return Err(extra("sigma"));
                }
                if self.dhr.is_some() {
                    return Err(extra("dhr"));
                }
                let f = self.f00_diffuse.ok_or_else(|| missing("f00_diffuse"))?;
                Surface::vegetation(index, f)
            }
        }
    }
}

/// A list of materials, as stored in TOML (`[[material]]` tables).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MaterialLibrary {
    /// The materials, in file order.
    #[serde(rename = "material")]
    pub materials: Vec<Material>,
}

/// Errors reading a material library.
#[derive(Debug, thiserror::Error)]
pub enum MaterialError {
    /// The TOML text does not parse or has wrong fields.
    #[error("material library: {0}")]
    Toml(#[from] toml::de::Error),
    /// The library could not be serialised.
    #[error("material library: {0}")]
    Serialize(#[from] toml::ser::Error),
    /// A material's parameters are out of range.
    #[error("material {name:?}: {source}")]
    Parameter {
        /// The material's name.
        name: String,
        /// What is out of range.
        source: ModelError,
    },
    /// Two materials share a name.
    #[error("material library: name {0:?} appears more than once")]
    Duplicate(String),
    /// No material of that name.
    #[error("unknown material {name:?}; known: {known}")]
    Unknown {
        /// The name asked for.
        name: String,
        /// The names available, comma-separated.
        known: String,
    },
}

impl MaterialLibrary {
    /// The built-in library (glass, black paint, asphalt, vegetation, Al, Cu, Au, Ag at 550 nm).
    pub fn builtin() -> Self {
        // The built-in file is checked by a unit test; a parse failure here is a bug.
        #[allow(clippy::expect_used)]
        MaterialLibrary::from_toml_str(BUILTIN_TOML).expect("built-in materials.toml is valid")
    }

    /// Parses and validates a library.
    pub fn from_toml_str(text: &str) -> Result<Self, MaterialError> {
        let lib: MaterialLibrary = toml::from_str(text)?;
        let mut seen = std::collections::HashSet::new();
        for m in &lib.materials {
            if !seen.insert(m.name.as_str()) {
                return Err(MaterialError::Duplicate(m.name.clone()));
            }
            m.surface().map_err(|source| MaterialError::Parameter {
                name: m.name.clone(),
                source,
            })?;
        }
        Ok(lib)
    }

    /// Serialises the library to TOML.
    pub fn to_toml_string(&self) -> Result<String, MaterialError> {
        Ok(toml::to_string_pretty(self)?)
    }

    /// Looks a material up by name.
    pub fn get(&self, name: &str) -> Result<&Material, MaterialError> {
        self.materials
            .iter()
            .find(|m| m.name == name)
            .ok_or_else(|| MaterialError::Unknown {
                name: name.to_string(),
                known: self
                    .materials
                    .iter()
                    .map(|m| m.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_has_the_eight_materials_and_round_trips() {
        let lib = MaterialLibrary::from_toml_str(BUILTIN_TOML).unwrap();
        for name in [
            "glass",
            "black_paint",
            "asphalt",
            "vegetation",
            "aluminium",
            "copper",
            "gold",
            "silver",
        ] {
            let m = lib.get(name).unwrap();
            assert_eq!(m.wavelength_nm, 550.0, "{name}");
            assert!(!m.source.trim().is_empty(), "{name} cites no source");
        }
        let text = lib.to_toml_string().unwrap();
        assert_eq!(MaterialLibrary::from_toml_str(&text).unwrap(), lib);
    }

    #[test]
    fn bad_entries_name_the_field() {
        let text = r#"
[[material]]
name = "x"
wavelength_nm = 550
n = 1.5
model = "microfacet"
sigma = 0.3
dhr = 1.7
source = "test"
"#;
        let e = MaterialLibrary::from_toml_str(text)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("dhr") && e.contains("1.7") && e.contains("[0, 1]"),
            "{e}"
        );
        let dup = format!("{text}{text}").replace("1.7", "0.1");
        let e = MaterialLibrary::from_toml_str(&dup)
            .unwrap_err()
            .to_string();
        assert!(e.contains("more than once"), "{e}");
        let unknown = text.replace("source", "colour = \"red\"\nsource");
        assert!(MaterialLibrary::from_toml_str(&unknown).is_err());
    }
}
