"""EtherCAT: masters (SOEM through pysoem, IgH CLI for SDO), the eRob component, the ring emulator."""
