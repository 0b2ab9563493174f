"""ZeroErr eRob servos: CiA402 over EtherCAT."""
