"""The plant: one definition of each linear model family's equations, used by simulation, identification and
diagnosis (docs/PLANT.md).

  model.py   the families (`eha`, `mechanical_axis`, `transfer_function`), their parameters (start value, fixed
             or free within bounds) and continuous state space
  zoh.py     the one exact zero-order-hold discretisation and the simulators
  file.py    the plant file's [plant] table -> Plant (`load_plant`)
"""
