"""The polarization compass: raw DoFP mosaic -> Stokes -> E-vectors -> sun vector -> heading.

Modules in the order of the data flow::

    pixels       raw mosaic, polarizer channels, pixel sets
    camera       camera rays (OpenCV) and the lens polarization models
    polarimetry  calibrated Stokes vectors and the pixel quality masks
    sunlight     the direct-sunlight term and its exact compensation
    lens         per-pixel lens constants of the estimators
    image        stage 1: one image's Stokes rows, noise and masks
    clouds       thin-cloud sky cells: DoP deficit, rotated AoP, fitted-sky DoP
    skypixels    stage 2: region of interest, starting sun, cloud cells, selection rules
    eigen        the eigen sun vector and its covariance
    prediction   the AoP a trial sun predicts; selection: which pixels enter the estimate
    skymodel     the joint ML's sky: the Berry neutral points, the camera-fixed polarization
    residual     the joint ML's AoP-orthogonal residual, its Jacobian and sums
    jointml      joint maximum likelihood of the sun and epsilon; losses: its robust losses
    solve        one image's joint ML: subsample, cloud cells, full-set step
    sectors      the jackknife over sky sectors
    solution     stage 3: the compensated or the traditional solution
    instrumental the camera-fixed polarization's part of the sigma
    heading      level frame, yaw, its variance, the 180 deg choice
    branch       the 180 deg branch without an ephemeris: elevation, brightness, prior
    measurement  Measurement and MeasureOptions; chain: the stages composed for one image
    measure      ``polins.measure``
    crlb         the Cramer-Rao bound of the yaw
    zenith       the zenith angle of polarization of a narrow field
    kernels      BLAS-free row products; the compiler of the passes in stokes_kernels,
                 selection_kernels, eigen_kernels, zenith_kernels
"""
