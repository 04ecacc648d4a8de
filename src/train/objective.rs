//! The training objective as named, weighted terms (spec §6, §9.3, §13): the trainer adds each
//! term it computes this step, the sum in the order added is the loss that is differentiated,
//! and every term's value reaches the log (`train_log.csv`) from one read-back per step.

use burn::tensor::Tensor;

use crate::model::anchors::host_values;

/// One term of the objective; its value is logged already weighted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Term {
    /// (1 − λ)·L1 + λ·(1 − SSIM).
    Photometric,
    /// Scale regulariser: mean volume of the spawned Gaussians (`loss.scale_reg`).
    Volume,
    /// GIFStream's gate regulariser (`loss.factor_reg`).
    Gate,
    /// Temporal smoothness against a nearby frame (`loss.smooth_reg`).
    Smoothness,
    /// Trajectory coherence between anchors of one cell (`loss.trajectory_coherence`).
    Coherence,
    /// AAFM's mask rate L_M (`aafm.mask_weight`).
    MaskRate,
    /// AAFM's conditional regularisation L_CR (`aafm.cr_weight`).
    ConditionalRegularization,
    /// The entropy models' bits (`compression.rate`'s λ).
    Rate,
    /// L1 on the second differences of the anchors' trajectory knots
    /// (`loss.trajectory_curvature`).
    Curvature,
}

impl Term {
    /// Every term, in the order of the log's columns.
    pub const ALL: [Term; 9] = [
        Term::Photometric,
        Term::Volume,
        Term::Gate,
        Term::Smoothness,
        Term::Coherence,
        Term::MaskRate,
        Term::ConditionalRegularization,
        Term::Rate,
        // Last: a resumed run's older log rows get empty cells at the end.
        Term::Curvature,
    ];

    /// The log's column name.
    pub fn name(self) -> &'static str {
        match self {
            Term::Photometric => "loss_photometric",
            Term::Volume => "loss_volume",
            Term::Gate => "loss_gate",
            Term::Smoothness => "loss_smoothness",
            Term::Coherence => "loss_coherence",
            Term::MaskRate => "loss_mask_rate",
            Term::ConditionalRegularization => "loss_cr",
            Term::Rate => "loss_rate",
            Term::Curvature => "loss_curvature",
        }
    }
}

/// The weighted terms of one step.
pub struct Objective {
    terms: Vec<(Term, Tensor<1>)>,
}

/// Host values of one step's objective.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObjectiveValues {
    pub total: f32,
    /// The terms computed this step, weighted, in the order added.
    pub terms: Vec<(Term, f32)>,
    /// The values of the `also` tensors given to [`Objective::read`].
    pub also: Vec<f32>,
}

impl Objective {
    pub fn new(photometric: Tensor<1>) -> Self {
        Self {
            terms: vec![(Term::Photometric, photometric)],
        }
    }

    /// Adds an already weighted [1] term.
    pub fn add(&mut self, term: Term, weighted: Tensor<1>) {
        self.terms.push((term, weighted));
    }

    /// The loss: the terms summed in the order added.
    pub fn total(&self) -> Tensor<1> {
        let mut terms = self.terms.iter().map(|(_, t)| t.clone());
        let first = terms.next().expect("the photometric term is always there");
        terms.fold(first, |sum, t| sum + t)
    }

    /// The values of `total` (the loss from [`Self::total`]), of every term and of each [1]
    /// tensor in `also`, in one read-back.
    pub fn read(&self, total: &Tensor<1>, also: &[Tensor<1>]) -> ObjectiveValues {
        let values: Vec<Tensor<1>> = std::iter::once(total)
            .chain(self.terms.iter().map(|(_, t)| t))
            .chain(also)
            .map(|t| t.clone().detach().reshape([1]))
            .collect();
        let host = host_values(&Tensor::cat(values, 0));
        let n = self.terms.len();
        ObjectiveValues {
            total: host[0],
            terms: (self.terms.iter().map(|(term, _)| *term))
                .zip(host[1..=n].iter().copied())
                .collect(),
            also: host[n + 1..].to_vec(),
        }
    }
}
