"""The paper's baselines (Sec. IV "Empirical Analysis") and DeepProMP behind one interface.

Six models, one code path for an evaluation harness::

    from deepprompt_ros.baselines.registry import MODEL_CLASSES
    from deepprompt_ros.evaluation.reconstruction import reconstruction_mse

    for cls in MODEL_CLASSES:
        model = cls().fit(train_ds, TrainConfig(...), val_ds)
        err = reconstruction_mse(model, test_ds, "low_dim")

==================  ==================================================================================
kind                model (module)
==================  ==================================================================================
``deepprompt``      ``DeepProMPModel`` (``deep_promp_model``): adapter over training.loop.train + DeepProMP
``promp``           ``ProMPModel`` (``promp_model``): adapter over the closed-form ProMP (``promp``), its
                    regularizer and via-point noise cross-validated on its training demos (``promp_selection``)
``cnmp``            ``CNMP`` (``concat``): one encoder on concatenated inputs, mean aggregation
``vae_cnmp``        ``VAECNMP`` (``concat``): the same with a Gaussian latent and an isotropic prior
``cnmp_indep``      ``CNMPIndep``, ``VAECNMPIndep`` (``concat``): trained with zero padding and
``vae_cnmp_indep``  sub-sampled input combinations
==================  ==================================================================================

``interface`` holds what every model answers (:class:`MovementPrimitiveModel`), ``registry`` the
list of model classes and ``load_model`` for any of their files.
"""
