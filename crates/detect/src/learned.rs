//! A camera's learned edge profile through the frames ([`CameraProfile`]): when it is learned,
//! how every tag of the camera is fitted with it, and how it is kept up to date (see
//! [`crate::refine::EdgeProfile`] for what it is, docs/accuracy.md for the figures).
//!
//! **Start.** The first frames' tags are fitted with the parametric model, as before, and
//! give their samples. As soon as they suffice (24 well-fitted edges and every node from
//! 2.5 px inside the edge to 1.25 px outside it — in the first frame of a camera that sees
//! ten tags), the profile is learned in that very frame by two rounds of the effective-PSF
//! iteration (fit the frame's tags with the profile, learn it again from those fits), and
//! the frame's tags are fitted with it before they leave the detector: from the first
//! measured frame on, every corner comes from the same model, so the switch makes no step
//! in the feed (a switch later in a test would move every edge by its old phase bias at once).
//!
//! **Running.** Every frame's fits add their samples; the profile is rebuilt after 1, 2, 4,
//! …, 64 frames and then every 64 frames, from sums that forget slowly (see
//! `refine::profile`): a rebuild changes the profile by its sampling noise only, far below
//! a pixel's noise, so it makes no step either, while a slow change of the optics is
//! followed. Tags found by a search (fitted by the library's refinement with the
//! parametric model) are fitted again with the profile; tags confirmed at their predicted
//! place are fitted with it directly. An edge the profile does not fit falls back to the
//! parametric model.
//!
//! **A rebuild beside the frame loop.** With the physical formation
//! (`TAGDEFLECT_EDGE_MODEL=formation` / `formation-sites`) a build searches the formation's
//! light, dozens of trials over 12 000 samples (0.3–1 s of a core), so a rebuild runs on a
//! worker thread over a copy of the learner taken at the frame it is due, and its profile is
//! taken into the fits [`BUILD_LAG_FRAMES`] frames of the camera later — waiting there if the
//! build has not finished. What is taken, and from which frame, depends only on the frame
//! count, never on how fast the worker ran: a replay gives the same positions run to run. A
//! rebuild due while one is under way waits for it (it is started at the frame the earlier one
//! is taken). The first profile (the start, below) is still learned in its frame. Without the
//! formation a rebuild is cheap and stays in its frame, as before.
//!
//! **Pixel classes.** Which class is fitted with its own profile (or its orientation's) is
//! decided when the profile is first learned, in that frame, by which profile predicts the
//! frame's held-out edges best (`refine::profile_classes`, [`ClassChoice`]), and kept by
//! every rebuild: a class changes its model never during a test, so it makes no step either
//! (a class not ready then stays on its parent's profile). The samples kept for the decision
//! are dropped once it is made.

use std::collections::{HashMap, HashSet};
use std::sync::{mpsc, Arc};

use super::refine::{
    refine_corners_warm, widening_switch, ClassChoice, EdgeMemory, EdgeProfile, ModelExcess, ProfileLearner, RefineOptions,
};
use super::Detection;
use tagdeflect_core::camera::Lens;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::TagFamily;

/// Frames between rebuilds once the schedule 1, 2, 4, … has reached it.
const MAX_REBUILD_INTERVAL: u64 = 64;

/// Frames of a camera from a rebuild started beside the frame loop to the frame its profile
/// is taken from (see the module docs): short enough that a 16-set test sees the rebuilt
/// profile. At 30 fps it is 0.27 s, less than a search takes beside the loop on a loaded
/// 2-core machine (0.3–1 s of a core), so there the loop still waits at that frame
/// (docs/performance.md, "The formation's search beside the frame loop").
const BUILD_LAG_FRAMES: u64 = 8;

/// A rebuild under way beside the frame loop: the frame count it is taken at, and where its
/// profile and the learner's copy (the formation's light found) will come.
type PendingBuild = (u64, mpsc::Receiver<(Option<EdgeProfile>, ProfileLearner)>);

/// A tag's key in a camera's memories.
pub(crate) type TagKey = (TagFamily, u32);

/// One camera's learned edge profile and its accumulation (see the module docs).
#[derive(Debug)]
pub(crate) struct CameraProfile {
    learner: ProfileLearner,
    profile: Option<Arc<EdgeProfile>>,
    /// Which profile each pixel class uses, decided when the profile was first learned.
    choice: Option<ClassChoice>,
    /// The profile fits' residuals against the camera's noise (the corners' σ widening);
    /// `None` (nothing gathered) when the widening is off ([`widening_switch`], read once
    /// when the camera is made).
    excess: Option<ModelExcess>,
    /// Frames since the profile was first learned.
    frames: u64,
    /// The frame count at which it is next rebuilt.
    next_build: u64,
    /// The rebuild under way beside the frame loop (see the module docs).
    pending: Option<PendingBuild>,
}

impl Default for CameraProfile {
    fn default() -> Self {
        Self {
            learner: ProfileLearner::default(),
            profile: None,
            choice: None,
            excess: widening_switch().then(ModelExcess::default),
            frames: 0,
            next_build: 0,
            pending: None,
        }
    }
}

impl CameraProfile {
    /// The profile, once learned.
    pub(crate) fn profile(&self) -> Option<Arc<EdgeProfile>> {
        self.profile.clone()
    }

    /// How much the corners' σ is to be widened for the profile fits' model error
    /// ([`ModelExcess::factor`]; 1 before the profile is learned and when the widening is
    /// off).
    pub(crate) fn sigma_factor(&self) -> f64 {
        self.excess.as_ref().map_or(1.0, ModelExcess::factor)
    }

    /// Adds a tag's fit to the residual sums, when they are gathered.
    fn add_excess(&mut self, image: &GrayImage, memory: &EdgeMemory) {
        if let Some(e) = self.excess.as_mut() {
            e.add_tag(image, memory);
        }
    }

    /// After a frame's detection: learns from its tags (`confirmed`: those fitted at their
    /// predicted place, whose fits are in `memories`), fits the searched ones with the
    /// profile, and learns or rebuilds the profile when due (see the module docs).
    pub(crate) fn after_frame(
        &mut self,
        image: &GrayImage,
        found: &mut [Detection],
        confirmed: &HashSet<TagKey>,
        memories: &mut HashMap<TagKey, EdgeMemory>,
        lens: Lens<'_>,
        opts: &RefineOptions,
    ) {
        let one_pass = RefineOptions { passes: 1, ..opts.clone() };
        let Some(profile) = self.profile.clone() else {
            for d in found.iter() {
                match memories.get(&(d.family, d.id)).filter(|_| confirmed.contains(&(d.family, d.id))) {
                    Some(m) => self.learner.add_tag(image, m),
                    None => self.learner.add_tag(image, &fit(image, d, lens, &one_pass, None).1),
                }
            }
            if let Some(first) = self.learner.build(None) {
                self.start(image, found, confirmed, memories, lens, &one_pass, first);
            }
            return;
        };
        for d in found.iter_mut() {
            let key = (d.family, d.id);
            match memories.get(&key).filter(|_| confirmed.contains(&key)) {
                Some(m) => {
                    self.learner.add_tag(image, m);
                    self.add_excess(image, m);
                }
                None => {
                    let (refit, m) = fit(image, d, lens, &one_pass, Some(&profile));
                    *d = refit;
                    self.learner.add_tag(image, &m);
                    self.add_excess(image, &m);
                }
            }
        }
        self.frames += 1;
        self.take_due_build();
        if self.frames >= self.next_build && self.pending.is_none() {
            self.rebuild();
            self.next_build = (2 * self.frames).min(self.frames + MAX_REBUILD_INTERVAL);
        }
    }

    /// Rebuilds the profile: in this frame, or with the formation's search beside the frame
    /// loop on a copy of the learner (see the module docs; in this frame if no thread starts).
    fn rebuild(&mut self) {
        if ProfileLearner::searches_formation() {
            let (mut copy, keep, (tx, rx)) = (self.learner.clone(), self.choice, mpsc::channel());
            let spawned = std::thread::Builder::new().name("edge-profile-build".into()).spawn(move || {
                let built = copy.build(keep.as_ref());
                let _ = tx.send((built, copy));
            });
            match spawned {
                Ok(_) => {
                    self.pending = Some((self.frames + BUILD_LAG_FRAMES, rx));
                    return;
                }
                Err(e) => tracing::warn!("cannot start an edge profile build beside the frame loop: {e}"),
            }
        }
        if let Some(p) = self.learner.build(self.choice.as_ref()) {
            self.profile = Some(Arc::new(p));
        }
    }

    /// Takes the rebuild under way into the fits when its frame has come, waiting for it if
    /// it has not finished (see the module docs).
    fn take_due_build(&mut self) {
        let Some((_, rx)) = self.pending.take_if(|(due, _)| self.frames >= *due) else { return };
        match rx.recv() {
            Ok((built, copy)) => {
                self.learner.take_search_start(&copy);
                if let Some(p) = built {
                    self.profile = Some(Arc::new(p));
                }
            }
            Err(_) => tracing::warn!("an edge profile build ended without a result"),
        }
    }

    /// Learns the profile in the frame where enough samples came (see the module docs) and
    /// fits the frame's tags with it.
    #[allow(clippy::too_many_arguments)]
    fn start(
        &mut self,
        image: &GrayImage,
        found: &mut [Detection],
        confirmed: &HashSet<TagKey>,
        memories: &mut HashMap<TagKey, EdgeMemory>,
        lens: Lens<'_>,
        one_pass: &RefineOptions,
        first: EdgeProfile,
    ) {
        let mut profile = Arc::new(first);
        for round in 0..2 {
            self.learner.clear();
            for d in found.iter() {
                self.learner.add_tag(image, &fit(image, d, lens, one_pass, Some(&profile)).1);
            }
            match self.learner.build(None) {
                Some(p) => profile = Arc::new(p),
                None => break,
            }
            tracing::debug!(round, edges = self.learner.edges(), "edge profile learned");
        }
        for d in found.iter_mut() {
            let (refit, m) = fit(image, d, lens, one_pass, Some(&profile));
            *d = refit;
            self.add_excess(image, &m);
            let key = (d.family, d.id);
            if confirmed.contains(&key) {
                memories.insert(key, m);
            }
        }
        tracing::debug!(choice = ?profile.choice(), "edge profile's pixel classes decided");
        self.choice = Some(profile.choice());
        self.learner.decided();
        self.profile = Some(profile);
        (self.frames, self.next_build) = (0, 1);
    }
}

/// `d` fitted again from its corners (one pass) with `profile` (or the parametric model):
/// the refitted tag (corners that fail keep their value) and what the fit left.
fn fit(
    image: &GrayImage,
    d: &Detection,
    lens: Lens<'_>,
    one_pass: &RefineOptions,
    profile: Option<&Arc<EdgeProfile>>,
) -> (Detection, EdgeMemory) {
    let mut memory = EdgeMemory::default().with_profile(profile.cloned());
    let mut refit = d.clone();
    refine_corners_warm(image, &mut refit, lens, one_pass, &mut memory);
    (refit, memory)
}
