"""Making the bundled victims: datasets of undream's own renders, training, model cards.

The top of the library: it renders with :mod:`undream.scene` and Mitsuba,
trains Hugging Face models that :mod:`undream.victims` loads, and scores them
with :mod:`undream.metrics`. Nothing in the attack path imports it.

- :mod:`undream.training.dataset`: rendered, labelled datasets with a held-out split
  (distribution ``v1``; ``v2`` in :mod:`undream.training.distribution_v2`; the
  disjoint bands in :mod:`undream.training.bands`, textures in
  :mod:`undream.training.textures`);
- :mod:`undream.training.train`: training the classifier and detector;
- :mod:`undream.training.evaluation`: their held-out numbers, overall and per
  weather, background and camera band;
- :mod:`undream.training.model_card`: training records, model cards and the
  checks of the shipped folders.
"""
