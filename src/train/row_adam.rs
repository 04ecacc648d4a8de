//! Adam whose state follows the rows of a parameter: anchors are added (densification, AAC),
//! removed (pruning) and re-initialised (relocation) while training, so the optimizer state must
//! grow, shrink and reset row by row, as gsplat's `_update_param_with_optimizer` does for
//! GIFStream. Burn's optimizers are keyed by parameter id with fixed shapes, hence this one
//! (spec §19).
//!
//! The update is PyTorch's `torch.optim.Adam` (no weight decay, no amsgrad):
//! m ← β1 m + (1 − β1) g, v ← β2 v + (1 − β2) g², p ← p − lr/(1 − β1^t) · m / (√v/√(1 − β2^t) + ε).
//! The step count t is one per parameter, as in PyTorch: new rows get zero moments, not their own t.

use crate::device_io::upload;
use crate::model::anchors::row_index;
use acags_kernels::fused_adam::{AdamStep, adam_update};
use burn::tensor::{Tensor, TensorData};

/// Adam hyper-parameters (GIFStream: betas (0.9, 0.999), eps 1e-15 for BS = 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

/// Adam state of one parameter tensor whose first dimension is the row (anchor) index.
#[derive(Clone, Debug)]
pub struct RowAdam<const D: usize> {
    pub config: AdamConfig,
    pub exp_avg: Tensor<D>,
    pub exp_avg_sq: Tensor<D>,
    pub step: u64,
}

impl<const D: usize> RowAdam<D> {
    /// Zero state shaped like `param`.
    pub fn new(param: &Tensor<D>, config: AdamConfig) -> Self {
        Self {
            config,
            exp_avg: param.zeros_like(),
            exp_avg_sq: param.zeros_like(),
            step: 0,
        }
    }

    /// One Adam step; returns the updated parameter (detached values; the caller re-marks it as
    /// requiring grad).
    pub fn step(&mut self, param: Tensor<D>, grad: Tensor<D>, lr: f64) -> Tensor<D> {
        self.fused_step(param, grad, &[lr])
    }

    /// The update as one fused op (`acags_kernels::fused_adam`: the 13 element-wise ops of
    /// m ← β1 m + (1 − β1) g, v ← β2 v + (1 − β2) g², p ← p − m / (√v/√(1 − β2^t) + ε) · lr/(1 − β1^t)
    /// in one pass, bit for bit the same on the CPU). `lr` holds one rate, or one per element of
    /// a row.
    fn fused_step(&mut self, param: Tensor<D>, grad: Tensor<D>, lr: &[f64]) -> Tensor<D> {
        let AdamConfig { beta1, beta2, eps } = self.config;
        self.step += 1;
        let t = self.step as i32;
        let bias1 = 1.0 - beta1.powi(t);
        let device = param.device();
        let rates: Vec<f32> = lr.iter().map(|&r| (r / bias1) as f32).collect();
        // One rate (every parameter but the knot tables): filled on the device, as a scalar op
        // sends its scalar, instead of one upload per parameter tensor and step.
        let rates = match rates[..] {
            [rate] => Tensor::<1>::full([1], rate, &device),
            _ => upload::<1, burn::tensor::Float>(TensorData::new(rates, [lr.len()]), &device),
        };
        // The state moves into the op (updated in place where it is not shared).
        let (param, exp_avg, exp_avg_sq) = adam_update(
            param,
            self.exp_avg.extract(),
            self.exp_avg_sq.extract(),
            grad,
            rates,
            AdamStep::new(beta1, beta2, eps, t),
        );
        self.exp_avg = exp_avg;
        self.exp_avg_sq = exp_avg_sq;
        param
    }

    pub fn rows(&self) -> usize {
        self.exp_avg.dims()[0]
    }

    /// Appends `count` rows of zero state (new anchors).
    pub fn grow(&mut self, count: usize) {
        if count == 0 {
            return;
        }
        let mut shape = self.exp_avg.dims();
        shape[0] = count;
        let zeros = Tensor::<D>::zeros(shape, &self.exp_avg.device());
        self.exp_avg = Tensor::cat(vec![self.exp_avg.clone(), zeros.clone()], 0);
        self.exp_avg_sq = Tensor::cat(vec![self.exp_avg_sq.clone(), zeros], 0);
    }

    /// Keeps the rows listed in `keep` (in that order): pruning, or any reordering of the rows.
    pub fn keep_rows(&mut self, keep: &[usize]) {
        let rows = self.rows();
        assert!(
            keep.iter().all(|&r| r < rows),
            "row index out of range (state has {rows} rows)"
        );
        let index = row_index(keep, &self.exp_avg.device());
        self.exp_avg = self.exp_avg.clone().select(0, index.clone());
        self.exp_avg_sq = self.exp_avg_sq.clone().select(0, index);
    }

    /// Zeroes the moments of the elements flagged in `zero` (row-major over the whole state):
    /// sub-row resets such as one slot's three offsets in the [N, 3·K] offsets state.
    pub fn reset_elements(&mut self, zero: &[bool]) {
        let shape = self.exp_avg.dims();
        assert_eq!(
            zero.len(),
            shape.iter().product::<usize>(),
            "reset flags must cover the state"
        );
        if !zero.iter().any(|&z| z) {
            return;
        }
        let keep: Vec<f32> = zero.iter().map(|&z| if z { 0.0 } else { 1.0 }).collect();
        let mask =
            upload::<D, burn::tensor::Float>(TensorData::new(keep, shape), &self.exp_avg.device());
        self.exp_avg = self.exp_avg.clone() * mask.clone();
        self.exp_avg_sq = self.exp_avg_sq.clone() * mask;
    }

    /// Zeroes the moments of the listed rows (a relocated Gaussian starts afresh).
    pub fn reset_rows(&mut self, rows: &[usize]) {
        if rows.is_empty() {
            return;
        }
        let n = self.rows();
        let mut keep = vec![1.0f32; n];
        for &r in rows {
            assert!(r < n, "row {r} out of range (state has {n} rows)");
            keep[r] = 0.0;
        }
        let mut shape = [1usize; D];
        shape[0] = n;
        let mask =
            upload::<D, burn::tensor::Float>(TensorData::new(keep, shape), &self.exp_avg.device());
        self.exp_avg = self.exp_avg.clone() * mask.clone();
        self.exp_avg_sq = self.exp_avg_sq.clone() * mask;
    }
}

impl RowAdam<2> {
    /// [`Self::step`] with its own rate for each column of the [rows, columns] parameter
    /// (the trajectory knots' per-knot schedule).
    pub fn step_columns(&mut self, param: Tensor<2>, grad: Tensor<2>, lr: &[f64]) -> Tensor<2> {
        let columns = param.dims()[1];
        assert_eq!(lr.len(), columns, "one rate per column");
        self.fused_step(param, grad, lr)
    }
}
