"""Making the bundled victims: datasets of undream's own renders, training, model cards.

The top of the library: it renders with :mod:`undream.scene` and Mitsuba,
trains Hugging Face models that :mod:`undream.victims` loads, and scores them
with :mod:`undream.metrics`. Nothing in the attack path imports it.

- :mod:`undream.training.dataset`: rendered, labelled datasets with a held-out split;
- :mod:`undream.training.train`: training and evaluating the classifier and detector;
- :mod:`undream.training.model_card`: training records, model cards and the
  checks of the shipped folders.
"""
