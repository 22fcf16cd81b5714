"""Multi-user factor-graph back-end (Nowicki & Skrzypczyński, Sensors 2019): factor models,
insertion policy, evolving WiFi map and the solver layer. Pure numpy/scipy, no ROS."""
