//! Entropy coding with `constriction`'s 64-bit-state rANS coder (32-bit words, 24-bit
//! probabilities); only the model glue is ours (spec §10 item 6, §19).
//!
//! - Integer symbols under a discretised zero-mean Gaussian whose σ is one of 256 log-spaced
//!   levels in [0.11, 64] (DCVC's / GIFStream's tables): the caller subtracts the rounded mean
//!   and picks a level per symbol. A table covers the attribute's whole range [−R, R] (R is
//!   written beside the stream) with every symbol given a non-zero probability, so nothing needs
//!   GIFStream's escape to bypass mode. Deviation, for that reason: tables are as wide as the data
//!   rather than ±50.
//! - Bits (gate and mask bitmaps) under a static Bernoulli per context, from counts written
//!   beside the stream; contexts whose bits are all equal cost nothing.
//!
//! Tables and scale levels are computed with `libm` (pure Rust) in f64, so encoder and decoder
//! compute identical tables and levels on every platform. A stream decodes exactly the symbols it was given and must end exactly where
//! the encoder stopped; a damaged stream is reported, never a panic (rANS can decode garbage
//! deterministically, the checksums of the container catch it first).

use std::collections::HashMap;

use anyhow::{Context, Result, bail, ensure};
use constriction::stream::model::DefaultContiguousCategoricalEntropyModel;
use constriction::stream::stack::DefaultAnsCoder;
use constriction::stream::{Decode, Encode};

pub const SCALE_LEVELS: usize = 256;
pub const SCALE_MIN: f64 = 0.11;
pub const SCALE_MAX: f64 = 64.0;
/// Largest |symbol| a table may cover (bounds the memory a damaged header could request).
pub const MAX_RADIUS: i32 = 1 << 20;

type Model = DefaultContiguousCategoricalEntropyModel;

/// Level of σ: floor((ln σ − ln 0.11)/Δ), clamped to [0, 255] (σ < 0.11 uses the 0.11 table).
pub fn scale_level(sigma: f64) -> u8 {
    if !(sigma > SCALE_MIN) {
        return 0;
    }
    let step = (libm::log(SCALE_MAX) - libm::log(SCALE_MIN)) / (SCALE_LEVELS - 1) as f64;
    ((libm::log(sigma) - libm::log(SCALE_MIN)) / step)
        .floor()
        .clamp(0.0, (SCALE_LEVELS - 1) as f64) as u8
}

/// σ of a level.
pub fn level_sigma(level: u8) -> f64 {
    let step = (libm::log(SCALE_MAX) - libm::log(SCALE_MIN)) / (SCALE_LEVELS - 1) as f64;
    libm::exp(libm::log(SCALE_MIN) + level as f64 * step)
}

/// Φ(x) of the standard normal (libm: identical on every platform).
pub(crate) fn normal_cdf(x: f64) -> f64 {
    0.5 * (1.0 + libm::erf(x / std::f64::consts::SQRT_2))
}

/// Probabilities of y ∈ [−R, R] under N(0, σ²) discretised to integers, tails folded into the
/// end symbols.
fn discretised_gaussian(sigma: f64, radius: i32) -> Vec<f64> {
    (-radius..=radius)
        .map(|y| {
            let hi = if y == radius {
                1.0
            } else {
                normal_cdf((y as f64 + 0.5) / sigma)
            };
            let lo = if y == -radius {
                0.0
            } else {
                normal_cdf((y as f64 - 0.5) / sigma)
            };
            (hi - lo).max(0.0)
        })
        .collect()
}

/// The 256 Gaussian tables over [−R, R], built on first use.
pub struct GaussianTables {
    radius: i32,
    tables: HashMap<u8, Model>,
}

impl GaussianTables {
    pub fn new(radius: i32) -> Result<Self> {
        ensure!(
            (1..=MAX_RADIUS).contains(&radius),
            "symbol range ±{radius} outside 1..={MAX_RADIUS}"
        );
        Ok(Self {
            radius,
            tables: HashMap::new(),
        })
    }

    pub fn radius(&self) -> i32 {
        self.radius
    }

    fn model(&mut self, level: u8) -> &Model {
        let radius = self.radius;
        self.tables.entry(level).or_insert_with(|| {
            let p = discretised_gaussian(level_sigma(level), radius);
            Model::from_floating_point_probabilities_fast(&p, None)
                .expect("a discretised Gaussian is a valid distribution")
        })
    }
}

fn words_to_bytes(words: &[u32]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

fn bytes_to_words(bytes: &[u8], what: &str) -> Result<Vec<u32>> {
    ensure!(
        bytes.len() % 4 == 0,
        "{what}: coded stream of {} bytes is not whole 32-bit words",
        bytes.len()
    );
    Ok(bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
        .collect())
}

/// Codes `symbols[i]` (already centred on its rounded mean) under the table of `levels[i]`.
pub fn encode_gaussian(
    symbols: &[i32],
    levels: &[u8],
    tables: &mut GaussianTables,
) -> Result<Vec<u8>> {
    assert_eq!(symbols.len(), levels.len(), "one level per symbol");
    let r = tables.radius;
    for &l in levels {
        tables.model(l);
    }
    let mut coder = DefaultAnsCoder::new();
    // ANS is a stack: encode in reverse so the decoder reads forward.
    for (&y, &l) in symbols.iter().zip(levels).rev() {
        ensure!(
            (-r..=r).contains(&y),
            "symbol {y} outside the coded range ±{r}"
        );
        let model = &tables.tables[&l];
        coder
            .encode_symbol((y + r) as usize, model)
            .context("rANS encoding failed")?;
    }
    let words = coder
        .into_compressed()
        .map_err(|_| anyhow::anyhow!("rANS backend failed"))?;
    Ok(words_to_bytes(&words))
}

/// Decodes `levels.len()` symbols written by [`encode_gaussian`] with the same levels.
pub fn decode_gaussian(
    bytes: &[u8],
    levels: &[u8],
    tables: &mut GaussianTables,
    what: &str,
) -> Result<Vec<i32>> {
    let mut decoder = GaussianDecoder::new(bytes, what)?;
    let out = levels
        .iter()
        .map(|&l| decoder.next(l, tables))
        .collect::<Result<Vec<_>>>()?;
    decoder.finish()?;
    Ok(out)
}

/// Symbol-by-symbol decoding, for models whose next level depends on what was decoded
/// (autoregressive contexts).
pub struct GaussianDecoder {
    coder: DefaultAnsCoder,
    what: String,
}

impl GaussianDecoder {
    pub fn new(bytes: &[u8], what: &str) -> Result<Self> {
        let words = bytes_to_words(bytes, what)?;
        let coder = DefaultAnsCoder::from_compressed(words)
            .map_err(|_| anyhow::anyhow!("{what}: coded stream ends in a zero word (damaged)"))?;
        Ok(Self {
            coder,
            what: what.to_string(),
        })
    }

    pub fn next(&mut self, level: u8, tables: &mut GaussianTables) -> Result<i32> {
        let r = tables.radius;
        let model = tables.model(level);
        let index = self
            .coder
            .decode_symbol(model)
            .map_err(|e| anyhow::anyhow!("{}: rANS decoding failed: {e:?}", self.what))?;
        Ok(index as i32 - r)
    }

    /// Fails unless the stream ended exactly after the last symbol.
    pub fn finish(self) -> Result<()> {
        if !self.coder.is_empty() {
            bail!(
                "{}: coded stream has data left after its last symbol (damaged or mismatched)",
                self.what
            );
        }
        Ok(())
    }
}

/// Per-context Bernoulli models from counts: `ones[c]` of `totals[c]` bits are set.
pub struct BitModels {
    models: Vec<Option<Model>>,
    /// Value of a context whose bits are all equal (coded with no bits).
    constant: Vec<Option<bool>>,
}

impl BitModels {
    pub fn new(ones: &[u32], totals: &[u32]) -> Result<Self> {
        ensure!(ones.len() == totals.len(), "bit model counts disagree");
        let mut models = Vec::new();
        let mut constant = Vec::new();
        for (&o, &t) in ones.iter().zip(totals) {
            ensure!(o <= t, "bit model: {o} ones of {t} bits");
            if o == 0 || o == t {
                models.push(None);
                constant.push(Some(o == t && t > 0));
            } else {
                let p1 = o as f64 / t as f64;
                models.push(Some(
                    Model::from_floating_point_probabilities_fast(&[1.0 - p1, p1], None)
                        .map_err(|_| anyhow::anyhow!("bit model: invalid probability {p1}"))?,
                ));
                constant.push(None);
            }
        }
        Ok(Self { models, constant })
    }

    /// Counts (ones, totals) of `bits` per context.
    pub fn count(bits: &[bool], contexts: &[usize], context_count: usize) -> (Vec<u32>, Vec<u32>) {
        let mut ones = vec![0u32; context_count];
        let mut totals = vec![0u32; context_count];
        for (&b, &c) in bits.iter().zip(contexts) {
            totals[c] += 1;
            ones[c] += b as u32;
        }
        (ones, totals)
    }

    pub fn encode(&self, bits: &[bool], contexts: &[usize]) -> Result<Vec<u8>> {
        let mut coder = DefaultAnsCoder::new();
        for (&b, &c) in bits.iter().zip(contexts).rev() {
            match &self.models[c] {
                Some(model) => coder
                    .encode_symbol(b as usize, model)
                    .context("rANS encoding failed")?,
                None => ensure!(
                    self.constant[c] == Some(b),
                    "bit in constant context {c} disagrees with its counts"
                ),
            }
        }
        let words = coder
            .into_compressed()
            .map_err(|_| anyhow::anyhow!("rANS backend failed"))?;
        Ok(words_to_bytes(&words))
    }

    pub fn decode(&self, bytes: &[u8], contexts: &[usize], what: &str) -> Result<Vec<bool>> {
        let words = bytes_to_words(bytes, what)?;
        let mut coder = DefaultAnsCoder::from_compressed(words)
            .map_err(|_| anyhow::anyhow!("{what}: coded stream ends in a zero word (damaged)"))?;
        let mut out = Vec::with_capacity(contexts.len());
        for &c in contexts {
            ensure!(c < self.models.len(), "{what}: context {c} out of range");
            out.push(match &self.models[c] {
                Some(model) => {
                    coder
                        .decode_symbol(model)
                        .map_err(|e| anyhow::anyhow!("{what}: rANS decoding failed: {e:?}"))?
                        == 1
                }
                None => self.constant[c].expect("constant context"),
            });
        }
        if !coder.is_empty() {
            bail!("{what}: coded stream has data left after its last bit (damaged or mismatched)");
        }
        Ok(out)
    }
}
